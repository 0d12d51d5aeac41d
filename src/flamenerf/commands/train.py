"""`flamenerf train`."""

from __future__ import annotations

# what the command runs is imported inside its function: the CLI imports every command
# module to build its --help (cli.py), which stays quick that way

import inspect
from pathlib import Path
from typing import Annotated, Any, Literal

import tyro

from flamenerf.config import PRESETS

PresetName = Literal[tuple(PRESETS)]  # the CLI's choices are the presets, whatever they are


def train(
    dataset: Annotated[Path, tyro.conf.Positional],
    out: Path = Path("runs/portrait"),
    preset: PresetName = "fast",
    steps: int | None = None,
    size: int | None = None,
    downscale: float | None = None,
    batch_rays: int | None = None,
    accumulate: int | None = None,
    face_reg_weight: float | None = None,
    face_depth_weight: float | None = None,
    moving_weight: float | None = None,
    expression_mode: Literal["masked", "none", "everywhere"] | None = None,
    head_region_scale: float | None = None,
    head_band: float | None = None,
    detail_levels: int | None = None,
    random_background: bool | None = None,
    view_dependent: bool | None = None,
    bf16: bool | None = None,
    seed: int | None = None,
    resume: bool = False,
    other_dataset: bool = False,
    device: str = "auto",
    threads: int = 0,
    nproc: int = 1,
) -> None:
    """Train a model on a dataset.

    Presets: `fast` (default; hash-grid field, trains in minutes on a CPU),
    `flame-in-nerf` (the paper's architecture and schedule; needs a GPU for days),
    `nerfies` (no expression input), `no-prior` (expression reaches every point).
    Checkpoints go to OUT/checkpoints every few hundred steps and on Ctrl-C; `--resume`
    continues exactly where the run stopped. TensorBoard logs: `tensorboard --logdir OUT/tb`.

    Example: flamenerf train scenes/portrait --out runs/fast --preset fast --size 128
    (the Nerfies variant of the same: add `--expression-mode none`)

    On N GPUs: add `--nproc N`, or launch it yourself (also across machines) with
    `torchrun --nproc_per_node=N -m flamenerf train ...` (docs/distributed.md).

    Args:
        dataset: Dataset directory (made by `flamenerf synth` or `flamenerf preprocess`).
        out: Run directory (config, checkpoints, TensorBoard logs, preview images).
        preset: Named configuration.
        steps: Override the preset's number of training steps.
        size: Train at this width in pixels (height follows the aspect ratio).
        downscale: Train at 1/downscale of the dataset resolution (alternative to --size).
        batch_rays: Rays per step (over all processes of a distributed run).
        accumulate: Compute each process's rays of a step in this many micro-batches
            (gradient accumulation: the same step in less memory).
        face_reg_weight: Weight of the face-region regularisation (paper: 0.1 to 10).
        face_depth_weight: Weight of the face-depth prior: rendering weight on rays through
            the tracked face mesh kept near its surface (0: off; docs/presets.md). Default:
            the preset's.
        moving_weight: Weight in the photometric loss of the pixels a dataset marks as
            background moving by itself (its `moving_path` masks: leaves, water,
            passers-by), between 0 (left out) and 1 (as any other pixel); they feed no
            depth prior either. Datasets without the masks are not affected. Default: 0.1.
        expression_mode: The ablations of any preset: `masked` (β through the spatial prior,
            FLAME-in-NeRF), `none` (no β: the Nerfies variant), `everywhere` (β at every
            point: no prior). Default: the preset's.
        head_region_scale: Datasets with head poses: grow the region that turns with the
            head (an ellipsoid around the face) by this factor. Long hair that turns with the
            head may want 1.3 (docs/head_pose.md). Default: 1.0.
        head_band: Datasets with head poses: the width of the blend from the head's motion to
            the still world, a fraction of the region's radius. Default: 0.6.
        detail_levels: Hash-grid presets: finer levels evaluated only in the head's region
            (0: off; `fast` has 4; docs/presets.md item 7). Default: the preset's.
        random_background: Composite each training ray over a random colour instead of
            black, so that a half-transparent room cannot pass for an opaque one (`fast`:
            on; docs/presets.md item 7). Default: the preset's.
        view_dependent: Whether colour sees the viewing direction. Off, cameras far off the
            capture path see truer colours (built-in scene) while captured views of real
            clips lose detail (docs/presets.md, "Less view dependence"). Default: on.
        bf16: Train the MLPs' layers in bfloat16 where this CPU multiplies it natively and
            faster (decided when the run starts, kept on resume; `fast`: on, 11 % shorter
            trainings on a Zen 4, the same figures; docs/presets.md). False: float32
            everywhere. Default: the preset's.
        seed: Seed of the initial weights and the ray sampling (repeat a training over
            seeds to see how much of a difference is noise). Default: the preset's (0).
        resume: Continue the run in OUT from its latest checkpoint (a run stopped before
            its first checkpoint starts again with its saved settings).
        other_dataset: With --resume: go on although DATASET's content differs from the
            dataset the run was trained on (refused otherwise; a moved or copied dataset is
            the same one).
        device: `auto` (CUDA when present), `cpu` or `cuda`.
        threads: CPU threads for torch (0 = default).
        nproc: Train on this many processes on this machine, one per GPU, through
            torchrun (DistributedDataParallel; gloo between CPU processes).
    """
    from flamenerf.config import override
    from flamenerf.config import preset as get_preset
    from flamenerf.data.dataset import load_dataset
    from flamenerf.errors import Interrupted, UserError
    from flamenerf.training.distributed import launch, launched_ranks
    from flamenerf.training.trainer import train as run_train

    ranks = launched_ranks()
    if nproc != 1:
        if nproc < 1:
            raise UserError(f"--nproc {nproc}: must be at least 1")
        if ranks.distributed:
            raise UserError("--nproc: this process is already one of a torchrun job; give "
                            "either --nproc or torchrun's --nproc_per_node")
        args = ["train", *_flags(locals(), skip={"nproc"})]
        rc, pressed = launch(nproc, args)
        if pressed:
            raise Interrupted(f"the run is saved in {out}; continue it with `flamenerf train "
                              f"{dataset} --out {out} --resume --nproc {nproc}`")
        if rc != 0:
            raise UserError(f"torchrun stopped with exit status {rc} (its output above says "
                            "which process failed, and why)")
        return
    cfg = get_preset(preset)
    if size is not None and downscale is not None:
        raise UserError("give either --size or --downscale, not both")
    if size is not None:
        ds = load_dataset(dataset, check_files=False)
        if size <= 0 or size > ds.intrinsics.w:
            raise UserError(f"--size {size}: must be in 1..{ds.intrinsics.w} (the dataset's width)")
        cfg.train.downscale = ds.intrinsics.w / size
    elif downscale is not None:
        if downscale < 1:
            raise UserError("--downscale must be >= 1")
        cfg.train.downscale = downscale
    for flag, v in (("--head-region-scale", head_region_scale), ("--head-band", head_band)):
        if v is not None and not v > 0:
            raise UserError(f"{flag} {v}: must be positive")
    if seed is not None and not 0 <= seed < 2 ** 63:
        raise UserError(f"--seed {seed}: must be in 0..2^63-1")
    if detail_levels is not None and detail_levels < 0:
        raise UserError(f"--detail-levels {detail_levels}: must be 0 or more")
    if face_reg_weight is not None and not face_reg_weight >= 0:
        raise UserError(f"--face-reg-weight {face_reg_weight}: must be 0 or more")
    if face_depth_weight is not None and not face_depth_weight >= 0:
        raise UserError(f"--face-depth-weight {face_depth_weight}: must be 0 or more")
    if moving_weight is not None and not 0 <= moving_weight <= 1:
        raise UserError(f"--moving-weight {moving_weight}: must be between 0 and 1")
    override(cfg, {"train.batch_rays": batch_rays, "train.face_reg_weight": face_reg_weight,
                   "train.face_depth_weight": face_depth_weight,
                   "train.moving_weight": moving_weight,
                   "model.expression_mode": expression_mode, "train.num_threads": threads,
                   "train.accumulate": accumulate, "model.head.region_scale": head_region_scale,
                   "model.head.band": head_band, "model.field.detail_levels": detail_levels,
                   "train.random_background": random_background,
                   "model.field.view_dependent": view_dependent, "train.bf16": bf16,
                   "train.seed": seed})
    if (preset == "fast" and batch_rays is None and not resume and ranks.main
            and device != "cpu" and _has_cuda()):
        print("note: on a GPU, --preset fast-gpu trains `fast` with eight times the rays per "
              "step in fewer steps (docs/presets.md)")
    if ranks.main and not resume:
        note_missing_landmarks(dataset)
    if ranks.main and resume:
        _note_ignored(out, preset, {
            "--size": size, "--downscale": downscale, "--batch-rays": batch_rays,
            "--accumulate": accumulate, "--face-reg-weight": face_reg_weight,
            "--face-depth-weight": face_depth_weight, "--moving-weight": moving_weight,
            "--expression-mode": expression_mode,
            "--head-region-scale": head_region_scale, "--head-band": head_band,
            "--detail-levels": detail_levels, "--random-background": random_background,
            "--view-dependent": view_dependent, "--bf16": bf16, "--seed": seed})
    res = run_train(dataset, out, cfg, resume=resume, device=device, steps=steps,
                    other_dataset=other_dataset)
    if not ranks.main:  # rank 0 speaks for the job
        if res.interrupted:
            raise SystemExit(130)
        return
    if res.interrupted:  # exit status 130, so that `train && eval` stops here
        again = (f"`flamenerf train {dataset} --out {out} --resume`" if not ranks.distributed
                 else "the same launch command and --resume")
        raise Interrupted(f"run saved at step {res.step} in {res.run_dir}; continue it with "
                          f"{again}")
    print(f"finished at step {res.step} in {res.seconds:.0f} s; run saved in {res.run_dir}")


def _has_cuda() -> bool:
    import torch

    return torch.cuda.is_available()


def _flags(values: dict[str, Any], skip: set[str]) -> list[str]:
    """This command's arguments as command-line flags again (for the torchrun it launches):
    the dataset, then every option that differs from its default."""
    sig = inspect.signature(train)
    out = [str(values["dataset"])]
    for name, p in sig.parameters.items():
        v = values[name]
        if name == "dataset" or name in skip or v == p.default:
            continue
        flag = "--" + name.replace("_", "-")
        if isinstance(v, bool) and isinstance(p.default, bool):  # a plain switch
            out.append(flag if v else "--no-" + name.replace("_", "-"))
        else:
            out += [flag, str(v)]
    return out


def note_missing_landmarks(dataset) -> None:
    """A built-in scene made before it named its face landmarks trains without face parts
    and mesh guide (silently otherwise): say so, and how to get them."""
    from flamenerf.data.dataset import load_dataset

    ds = load_dataset(dataset, check_files=False)
    if ds.expression_kind == "synthetic" and ds.face_landmarks is None:
        print(f"note: {dataset} names no face landmarks (made by an older `flamenerf synth`): "
              "its controls are fitted without face parts and the mesh guide stays off; "
              "make it again with `flamenerf synth` for both (docs/synthetic_scene.md)")


def _note_ignored(out: Path, preset: str, flags: dict[str, Any]) -> None:
    """On --resume the run keeps its own settings: say which of the given ones it ignores."""
    from flamenerf.errors import UserError
    from flamenerf.io import read_json
    from flamenerf.training.checkpoint import latest_checkpoint

    if latest_checkpoint(out) is None and not (out / "config.json").is_file():
        return  # nothing to resume: the flags make the run
    try:
        meta = read_json(out / "config.json")
    except UserError:
        return  # the trainer reports a damaged config.json
    kept = meta.get("preset") if isinstance(meta, dict) else None
    ignored = [f"{k} {v}" for k, v in flags.items() if v is not None]
    other = kept is not None and preset != kept
    # the default preset cannot be told from one given: a run of another preset is named
    # as such, and a --preset other than the default is listed as ignored
    if other and preset != inspect.signature(train).parameters["preset"].default:
        ignored.insert(0, f"--preset {preset}")
    if ignored or other:
        print(f"note: --resume continues {out}{f', a `{kept}` run,' if other else ''} with "
              f"its own settings{'; ignored: ' + ', '.join(ignored) if ignored else ''} "
              f"(only --steps changes a resumed run)")
