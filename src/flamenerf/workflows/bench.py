"""The synthetic benchmark behind `flamenerf bench`: scene -> three runs with equal budgets
-> evaluation -> a Markdown report with the table, timings, the machine and the figure
"Why use the Spatial Ray Prior?" (fixed camera, expression changes, |difference| images
with and without the prior).

Methods (one model class; they differ only in `cfg.model.expression_mode`):
  FLAME-in-NeRF  "masked": β only on rays through the face silhouette (the paper);
  Nerfies        "none": no β input;
  No prior       "everywhere": β reaches every sample point (the ablation).
With CUDA they use the presets flame-in-nerf / nerfies / no-prior (the paper's
architecture). On a CPU all three use the `fast` preset's machinery (hash grid, small
warp, cheap sampling; docs/presets.md) with the expression mode set as above, because the
paper's architecture takes days there. `--machinery` overrides the choice.
"""

from __future__ import annotations

# imported to build `flamenerf --help` (BenchOptions): training, evaluation and the synthetic
# scene are imported inside the functions that run them

import json
import os
import platform
import re
import shutil
import subprocess
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

import tyro

from flamenerf.config import Config, override, preset
from flamenerf.errors import UserError
from flamenerf.data.dataset import load_dataset
from flamenerf.images import abs_diff, hstack, resize_to_height, text_strip, titled_row, vstack
from flamenerf.io import atomic_write_text, read_json, save_png, write_json
from flamenerf.outdir import check_replaceable
from flamenerf.runtime import pick_device, set_threads

METHODS = [  # (run name, expression mode, the preset used with the paper's machinery)
    ("flame-in-nerf", "masked", "flame-in-nerf"),
    ("nerfies", "none", "nerfies"),
    ("no-prior", "everywhere", "no-prior"),
]


@dataclass
class BenchOptions:
    """Options of `flamenerf bench` (its flags, same names; the help text below is their
    --help).

    Attributes:
        out: Report directory.
        work: Working directory for the scene and the three runs.
        scene: Use this existing dataset (with the built-in scene's splits) instead of
            making the built-in scene in WORK/scene.
        scene_size: Width and height of the built-in scene in pixels.
        frames: Capture frames of the scene (val is every 10th).
        seed: Scene seed (also the ω fit's).
        entangled: Make the scene whose capture moves the controls only in fixed groups
            (`synth --entangled`), to measure controls alone.
        train_size: Train (and evaluate) at this width (default: 64 on CPU, the scene's on
            CUDA).
        steps: Training steps of every method (default: the preset's, `fast`: 1800; 20000
            with the paper's presets).
        batch_rays: Rays per training step (default: the preset's).
        fit_steps: Steps of the held-out ω fit (default: 2000 on CUDA, 300 on CPU).
        fit_batch_rays: Rays per step of the ω fit.
        machinery: `auto` (paper presets with CUDA, `fast` otherwise), `fast` or `paper`.
        device: `auto` (CUDA when present), `cpu` or `cuda`.
        threads: CPU threads for torch (0 = default).
        overwrite: Re-make the scene and retrain runs whose settings differ.
        figure_columns: Expression columns of the prior-ablation figure (not a flag).
    """

    out: Path = Path("docs/bench")
    work: Path = Path("runs/bench")
    scene: Path | None = None
    scene_size: int = 128
    frames: int = 120
    seed: int = 0
    entangled: bool = False
    train_size: int | None = None
    steps: int | None = None
    batch_rays: int | None = None
    fit_steps: int | None = None
    fit_batch_rays: int = 1024
    machinery: Literal["auto", "fast", "paper"] = "auto"
    device: str = "auto"
    threads: int = 0
    overwrite: bool = False
    figure_columns: Annotated[int, tyro.conf.Suppress] = 6


def machine_description() -> dict[str, Any]:
    import torch

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem_gb = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                mem_gb = round(int(line.split()[1]) / 2**20, 1)
    except OSError:
        pass
    gpu = None
    if torch.cuda.is_available():
        p = torch.cuda.get_device_properties(0)
        gpu = f"{p.name}, {p.total_memory / 2**30:.0f} GiB"
    return {"cpu": cpu, "cpu_cores": os.cpu_count(), "torch_threads": torch.get_num_threads(),
            "memory_gb": mem_gb, "gpu": gpu, "torch": torch.__version__,
            "python": platform.python_version(), "os": platform.platform()}


def git_commit() -> str | None:
    try:
        r = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                           text=True, cwd=Path(__file__).parent, timeout=10)
        return r.stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        return None


def method_configs(machinery: str, steps: int | None, batch_rays: int | None,
                   downscale: float) -> dict[str, Config]:
    """The three methods' configs with equal budgets (steps, rays per step, resolution).
    The warp's coarse-to-fine schedule is a fraction of the run, so it scales with `steps`."""
    cfgs = {}
    for name, mode, paper_preset in METHODS:
        if machinery == "paper":
            cfg = preset(paper_preset)
        else:
            cfg = preset("fast")
            cfg.model.expression_mode = mode
        cfgs[name] = override(cfg, {"train.steps": steps, "train.batch_rays": batch_rays,
                                    "train.downscale": downscale})
    return cfgs


def _comparable(cfg: dict) -> dict:
    d = json.loads(json.dumps(cfg))
    d.get("train", {}).pop("num_threads", None)
    return d


def _prepare_scene(o: BenchOptions, log) -> tuple[Path, float, bool]:
    from flamenerf.synthetic.scene import SOURCE_NAME, make_scene

    if o.scene is not None:
        load_dataset(o.scene)  # fail early, naming the file, if it is not a dataset
        log(f"scene: using {o.scene}")
        return Path(o.scene), 0.0, True
    scene = o.work / "scene"
    if scene.exists() and not o.overwrite:
        ds = load_dataset(scene, check_files=False)
        src = ds.source or {}
        want = {"name": SOURCE_NAME, "size": o.scene_size, "frames": o.frames, "seed": o.seed,
                "entangled": o.entangled}
        have = {k: src.get(k) for k in want}
        have["entangled"] = bool(have["entangled"])
        if have != want:
            raise UserError(f"{scene}: holds another scene ({have}, want {want}); pass "
                            "--overwrite to re-make it, or another --work")
        log(f"scene: reusing {scene}")
        return scene, 0.0, True
    log(f"scene: making the built-in scene at {o.scene_size} px, {o.frames} frames -> {scene}")
    t0 = time.perf_counter()
    make_scene(scene, seed=o.seed, size=o.scene_size, frames=o.frames, overwrite=True,
               entangled=o.entangled)
    return scene, time.perf_counter() - t0, False


def _train(name: str, cfg: Config, scene: Path, o: BenchOptions, log) -> dict[str, Any]:
    return timed_train(o.work / "runs" / name, cfg, scene, o.device, o.overwrite, log)


def timed_train(run_dir: Path, cfg: Config, scene: Path, device: str = "auto",
                overwrite: bool = False, log=print) -> dict[str, Any]:
    """Train `cfg` on `scene` in `run_dir` for a benchmark: a finished run with the same
    settings is reused and an unfinished one resumed, its training time summed over the
    invocations that trained it (RUN/bench_timing.json); other settings are an error unless `overwrite`.
    -> {"run", "train_seconds", "step", "reused"}."""
    from flamenerf.training.checkpoint import latest_checkpoint
    from flamenerf.training.trainer import train

    timing_file = run_dir / "bench_timing.json"
    prev = 0.0
    if latest_checkpoint(run_dir) is not None:
        from flamenerf.training.trainer import settle_dataset_defaults

        settle_dataset_defaults(cfg, load_dataset(scene))  # as the saved run has them
        saved = read_json(run_dir / "config.json")
        want = cfg.to_dict()
        # bf16 is settled when a run starts (on where the CPU does it faster, trainer.py): a
        # run asked for it holds False where it did not pay
        if want["train"].get("bf16") and saved.get("config", {}).get("train", {}).get(
                "bf16") is False:
            want["train"]["bf16"] = False
        same = (_comparable(saved.get("config", {})) == _comparable(want)
                and Path(saved.get("dataset", "")) == scene.resolve())
        if not same:
            if not overwrite:
                raise UserError(f"{run_dir}: holds a run with other settings; pass --overwrite "
                                "to retrain it, or another --work")

            check_replaceable(run_dir, "run")  # --overwrite removes only what we wrote
            shutil.rmtree(run_dir)
        elif timing_file.exists():
            prev = float(read_json(timing_file).get("train_seconds", 0.0))
    ck = latest_checkpoint(run_dir)
    resume = ck is not None
    start = int(re.search(r"step-(\d+)", ck.name).group(1)) if ck is not None else 0
    log(f"train {run_dir.name}: {cfg.train.steps} steps x {cfg.train.batch_rays} rays "
        f"({'resuming' if resume else 'new run'}) -> {run_dir}")
    res = train(scene, run_dir, cfg, resume=resume, device=device, steps=cfg.train.steps)
    if res.interrupted:
        raise KeyboardInterrupt
    total = prev + res.seconds
    atomic_write_text(timing_file, json.dumps({"train_seconds": total, "step": res.step}))
    return {"run": str(run_dir), "train_seconds": total, "step": res.step,
            "reused": start >= cfg.train.steps}


def run_bench(o: BenchOptions, log=print) -> dict[str, Any]:

    from flamenerf.evaluation.protocol import EvalOptions, evaluate_run
    from flamenerf.training.run import load_run

    set_threads(o.threads)
    dev = pick_device(o.device)
    machinery = o.machinery if o.machinery != "auto" else ("paper" if dev.type == "cuda"
                                                            else "fast")
    t_all = time.perf_counter()
    scene, synth_s, scene_reused = _prepare_scene(o, log)
    ds = load_dataset(scene)
    train_size = o.train_size or (ds.intrinsics.w if dev.type == "cuda"
                                  else min(64, ds.intrinsics.w))
    if not 1 <= train_size <= ds.intrinsics.w:
        raise UserError(f"--train-size {train_size}: must be in 1..{ds.intrinsics.w}")
    steps = o.steps if o.steps is not None else (20_000 if machinery == "paper" else None)
    cfgs = method_configs(machinery, steps, o.batch_rays, ds.intrinsics.w / train_size)
    for cfg in cfgs.values():
        cfg.train.num_threads = o.threads
    fit_steps = o.fit_steps if o.fit_steps is not None else (2000 if dev.type == "cuda"
                                                             else 300)
    eopts = EvalOptions(fit_steps=fit_steps, fit_batch_rays=o.fit_batch_rays, seed=o.seed)
    methods: dict[str, Any] = {}
    for name, cfg in cfgs.items():
        methods[name] = _train(name, cfg, scene, o, log)
    results = {}
    for name in cfgs:
        run = load_run(methods[name]["run"], o.device)
        log(f"eval {name}")
        res = evaluate_run(run, ds, eopts, Path(methods[name]["run"]) / "eval", quiet=True,
                           log=lambda s: log(f"  {s}"))
        methods[name]["eval_seconds"] = res["seconds"]
        results[name] = res
    log("figure: why use the spatial ray prior?")
    o.out.mkdir(parents=True, exist_ok=True)
    fig_name = _prior_figure(o, ds, methods, train_size)
    cfg0 = next(iter(cfgs.values()))
    report = {
        "format": "flamenerf-bench", "version": 1,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "command": "flamenerf bench " + " ".join(_cli_args(o)),
        "commit": git_commit(),
        "machine": machine_description(),
        "device": str(dev),
        "machinery": machinery,
        "options": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(o).items()},
        "scene": {"path": str(scene), "size": ds.intrinsics.w,
                  "builtin": (ds.source or {}).get("name") == "flamenerf synth",
                  "frames": len(ds.splits.get("train", [])) + len(ds.splits.get("val", [])),
                  "splits": {k: len(v) for k, v in ds.splits.items()},
                  "synth_seconds": synth_s, "reused": scene_reused},
        "training": {"resolution": [round(ds.intrinsics.w / cfg0.train.downscale),
                                    round(ds.intrinsics.h / cfg0.train.downscale)],
                     "steps": cfg0.train.steps, "batch_rays": cfg0.train.batch_rays,
                     "presets": {n: c.preset for n, c in cfgs.items()},
                     "field": cfg0.model.field.kind, "sampler": cfg0.model.sampler.kind,
                     "expression_modes": {n: c.model.expression_mode for n, c in cfgs.items()}},
        "eval": asdict(eopts),
        "methods": methods,
        "results": results,
        "figure": fig_name,
        "total_seconds": time.perf_counter() - t_all,
    }
    write_json(o.out / "bench.json", report)
    atomic_write_text(o.out / "README.md", bench_markdown(report))
    return report


def _cli_args(o: BenchOptions) -> list[str]:
    d = BenchOptions()
    args = []
    for k, v in asdict(o).items():
        if v != getattr(d, k):
            flag = "--" + k.replace("_", "-")
            args += [flag] if v is True else [flag, str(v)]
    return args


def _prior_figure(o: BenchOptions, ds, methods: dict[str, Any], train_size: int) -> str | None:
    """The paper's figure 'Why use the Spatial Ray Prior?' from the leakage split: rows
    ground truth, then for FLAME-in-NeRF and No prior each a render row and a
    |render - neutral| x4 row; columns neutral and controls at full strength."""
    import torch

    from flamenerf.data.scene import FrameSet
    from flamenerf.evaluation.protocol import DIFF_GAIN, pick_sweep_frames, render_frames
    from flamenerf.training.run import load_run

    if not ds.splits.get("leakage") or len(ds.splits["leakage"]) < 2:
        return None
    runs = {n: load_run(methods[n]["run"], o.device) for n in ("flame-in-nerf", "no-prior")}
    intr = runs["flame-in-nerf"].train_intrinsics(ds)
    fs_all = FrameSet(ds, ds.split("leakage"), intr)
    idx = pick_sweep_frames(fs_all, o.figure_columns)
    fs = FrameSet(ds, [fs_all.frames[i] for i in idx], intr)
    scale = max(1, round(128 / intr.h))
    h = intr.h * scale

    def row(imgs):
        return hstack([resize_to_height(i, h) for i in imgs], gap=2)

    labels = ["neutral"] + [str(fs.frames[i].extra.get("leakage_control")) for i in
                            range(1, fs.n)]
    gt_row = titled_row([resize_to_height(i, h) for i in fs.images.numpy()], labels, gap=2)
    width = gt_row.shape[1]
    parts = [text_strip("ground truth", width), gt_row]
    for name, title in (("flame-in-nerf", "with the spatial ray prior (FLAME-in-NeRF)"),
                        ("no-prior", "without the prior")):
        r = runs[name]
        w0, p0 = r.frame_codes(0)
        with torch.no_grad():
            preds = render_frames(r.model, fs, w0.expand(fs.n, -1), p0.expand(fs.n, -1))
        parts += [text_strip(f"{title}: render", width), row(preds),
                  text_strip(f"{title}: |render - neutral| x{DIFF_GAIN:g}", width),
                  row([abs_diff(p, preds[0], DIFF_GAIN) for p in preds])]
    fig = vstack(parts, gap=2)
    name = "prior_ablation.png"
    save_png(o.out / name, fig)
    return name


def bench_markdown(rep: dict[str, Any]) -> str:
    from flamenerf.evaluation.report import compare_markdown, fmt

    m = rep["machine"]
    tr = rep["training"]
    sc = rep["scene"]
    names = list(rep["results"])
    res = [rep["results"][n] for n in names]
    modes = tr["expression_modes"]
    L = ["# Synthetic benchmark", "",
         f"Made by `{rep['command']}` on {rep['created'][:10]}"
         + (f" at commit `{rep['commit']}`" if rep.get("commit") else "") + ".", "",
         "## Machine", "",
         f"- CPU: {m['cpu']}, {m['cpu_cores']} cores (torch threads: {m['torch_threads']})",
         f"- memory: {m['memory_gb']} GiB; GPU: {m['gpu'] or 'none'}; ran on `{rep['device']}`",
         f"- torch {m['torch']}, Python {m['python']}, {m['os']}", "",
         "## Setup", "",
         ("- Scene: the built-in synthetic portrait (`flamenerf synth`), " if sc.get("builtin")
          else f"- Scene: the dataset `{sc['path']}`, ")
         + f"{sc['size']} px, {sc['frames']} capture frames; splits: "
         + ", ".join(f"{k} {v}" for k, v in sc["splits"].items()) + ".",
         f"- Training, equal budgets for all methods: {tr['steps']} steps x {tr['batch_rays']} "
         f"rays at {tr['resolution'][0]}x{tr['resolution'][1]}.",
    ]
    if rep["machinery"] == "fast":
        L.append(f"- Machinery: the `fast` preset ({tr.get('field')} field, small SE(3) warp, "
                 f"{tr.get('sampler')} sampler) for all three methods, differing only in "
                 "`cfg.model.expression_mode`: "
                 + ", ".join(f"{n} = `{modes[n]}`" for n in names)
                 + ". (The paper's architecture, presets `flame-in-nerf`/`nerfies`/`no-prior`, "
                 "is used when CUDA is present.)")
    else:
        L.append("- Presets: " + ", ".join(f"`{tr['presets'][n]}` (`{modes[n]}`)" for n in names)
                 + " (the paper's architecture).")
    e = rep["eval"]
    L += [f"- Evaluation (`flamenerf eval`, docs/evaluation.md): held-out `val` frames with "
          f"only ω fitted ({e['fit_steps']} steps x {e['fit_batch_rays']} rays; the paper: "
          "2000), at the training resolution; re-animation against ground truth; background "
          f"leakage outside the face masks dilated by {e['leakage_dilate_px']} px.", "",
          "## Results", "", compare_markdown(res),
          "MSE/PSNR/SSIM: held-out frames (the paper's Table 1 protocol). PSNR face / bg: "
          "inside / outside the face mask. Re-anim.: frame 0's codes with novel expressions "
          "from novel cameras, against the scene's ground truth. Leakage: mean |change| "
          "(0-255) of background pixels while only the expression changes (lower is better; "
          "the ground truth's is "
          + fmt(res[0].get("leakage", {}).get("gt_mean") if res[0].get("leakage") else None)
          + ").", ""]
    if rep.get("figure"):
        L += ["## Why use the spatial ray prior?", "",
              f"![prior ablation]({rep['figure']})", "",
              "Fixed camera (frame 0's), frame 0's codes; each column changes one expression "
              "control to full strength. The difference rows show |render - neutral render| "
              "x4: with the prior only the face changes; without it the expression also moves "
              "the background (cf. the paper's figure).", ""]

    def secs(x):
        return fmt(x, 0 if x >= 10 else 1)

    L += ["## Timings", "", "| stage | seconds |", "|---|--:|",
          f"| make the scene | {secs(sc['synth_seconds'])}"
          + (" (reused)" if sc["reused"] else "") + " |"]
    for n in names:
        mm = rep["methods"][n]
        L.append(f"| train {n} | {secs(mm['train_seconds'])}"
                 + (" (reused)" if mm.get("reused") else "") + " |")
    for n in names:
        L.append(f"| eval {n} | {secs(rep['methods'][n]['eval_seconds'])} |")
    L += [f"| total (this invocation) | {secs(rep['total_seconds'])} |", "",
          "Per-run details: `RUN/eval/metrics.md` under "
          f"`{Path(rep['methods'][names[0]]['run']).parent}`; all numbers: `bench.json`."]
    return "\n".join(L) + "\n"
