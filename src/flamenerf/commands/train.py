"""`flamenerf train`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

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
    face_reg_weight: float | None = None,
    expression_mode: Literal["masked", "none", "everywhere"] | None = None,
    resume: bool = False,
    device: str = "auto",
    threads: int = 0,
) -> None:
    """Train a model on a dataset.

    Presets: `fast` (default; hash-grid field, trains in minutes on a CPU),
    `flame-in-nerf` (the paper's architecture and schedule; needs a GPU for days),
    `nerfies` (no expression input), `no-prior` (expression reaches every point).
    Checkpoints go to OUT/checkpoints every few hundred steps and on Ctrl-C; `--resume`
    continues exactly where the run stopped. TensorBoard logs: `tensorboard --logdir OUT/tb`.

    Example: flamenerf train scenes/portrait --out runs/fast --preset fast --size 128
    (the Nerfies variant of the same: add `--expression-mode none`)

    Args:
        dataset: Dataset directory (made by `flamenerf synth` or `flamenerf preprocess`).
        out: Run directory (config, checkpoints, TensorBoard logs, preview images).
        preset: Named configuration.
        steps: Override the preset's number of training steps.
        size: Train at this width in pixels (height follows the aspect ratio).
        downscale: Train at 1/downscale of the dataset resolution (alternative to --size).
        batch_rays: Rays per step.
        face_reg_weight: Weight of the face-region regularisation (paper: 0.1 to 10).
        expression_mode: The ablations of any preset: `masked` (β through the spatial prior,
            FLAME-in-NeRF), `none` (no β: the Nerfies variant), `everywhere` (β at every
            point: no prior). Default: the preset's.
        resume: Continue the run in OUT from its latest checkpoint.
        device: `auto` (CUDA when present), `cpu` or `cuda`.
        threads: CPU threads for torch (0 = default).
    """
    from flamenerf.config import override
    from flamenerf.config import preset as get_preset
    from flamenerf.data.dataset import load_dataset
    from flamenerf.errors import Interrupted, UserError
    from flamenerf.training.trainer import train as run_train

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
    override(cfg, {"train.batch_rays": batch_rays, "train.face_reg_weight": face_reg_weight,
                   "model.expression_mode": expression_mode, "train.num_threads": threads})
    res = run_train(dataset, out, cfg, resume=resume, device=device, steps=steps)
    if res.interrupted:  # exit status 130, so that `train && eval` stops here
        raise Interrupted(f"run saved at step {res.step} in {res.run_dir}; continue it with "
                          f"`flamenerf train {dataset} --out {out} --resume`")
    print(f"finished at step {res.step} in {res.seconds:.0f} s; run saved in {res.run_dir}")
