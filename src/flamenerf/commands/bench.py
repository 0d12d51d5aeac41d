"""`flamenerf bench`."""

from __future__ import annotations

from pathlib import Path
from typing import Literal


def bench(
    out: Path = Path("docs/bench"),
    work: Path = Path("runs/bench"),
    scene: Path | None = None,
    scene_size: int = 128,
    frames: int = 120,
    seed: int = 0,
    train_size: int | None = None,
    steps: int | None = None,
    batch_rays: int | None = None,
    fit_steps: int | None = None,
    fit_batch_rays: int = 1024,
    machinery: Literal["auto", "fast", "paper"] = "auto",
    device: str = "auto",
    threads: int = 0,
    overwrite: bool = False,
) -> None:
    """Run the synthetic benchmark end to end and write a Markdown report.

    Makes the built-in scene (or reuses WORK/scene), trains FLAME-in-NeRF, the Nerfies
    baseline and the no-prior ablation with equal budgets (WORK/runs/NAME; finished or
    interrupted runs are resumed, not retrained), evaluates all three (`flamenerf eval`)
    and writes OUT/README.md (table, timings, machine, the figure "Why use the Spatial Ray
    Prior?"), OUT/prior_ablation.png and OUT/bench.json. With CUDA the three use the
    paper's presets (flame-in-nerf, nerfies, no-prior); on a CPU they all use the `fast`
    preset's machinery with `cfg.model.expression_mode` = masked / none / everywhere.

    Example: flamenerf bench --scene-size 64 --frames 40 --steps 300 --out /tmp/bench

    Args:
        out: Report directory.
        work: Working directory for the scene and the three runs.
        scene: Use this existing dataset (with the built-in scene's splits) instead of
            making the built-in scene in WORK/scene.
        scene_size: Width and height of the built-in scene in pixels.
        frames: Capture frames of the scene (val is every 10th).
        seed: Scene seed (also the ω fit's).
        train_size: Train (and evaluate) at this width (default: 64 on CPU, the scene's on
            CUDA).
        steps: Training steps of every method (default: the preset's, `fast`: 680; 20000
            with the paper's presets).
        batch_rays: Rays per training step (default: the preset's).
        fit_steps: Steps of the held-out ω fit (default: 2000 on CUDA, 300 on CPU).
        fit_batch_rays: Rays per step of the ω fit.
        machinery: `auto` (paper presets with CUDA, `fast` otherwise), `fast` or `paper`.
        device: `auto` (CUDA when present), `cpu` or `cuda`.
        threads: CPU threads for torch (0 = default).
        overwrite: Re-make the scene and retrain runs whose settings differ.
    """
    from flamenerf.errors import UserError
    from flamenerf.evaluation.bench import BenchOptions, run_bench
    from flamenerf.evaluation.report import compare_markdown

    for name, v in (("--scene-size", scene_size), ("--frames", frames),
                    ("--train-size", train_size), ("--steps", steps),
                    ("--batch-rays", batch_rays), ("--fit-batch-rays", fit_batch_rays)):
        if v is not None and v < 1:
            raise UserError(f"{name} {v}: must be at least 1")
    if scene_size < 16:
        raise UserError(f"--scene-size {scene_size}: must be at least 16")
    if fit_steps is not None and fit_steps < 0:
        raise UserError(f"--fit-steps {fit_steps}: must be >= 0")
    opts = BenchOptions(out=out, work=work, scene=scene, scene_size=scene_size, frames=frames, seed=seed,
                        train_size=train_size, steps=steps, batch_rays=batch_rays,
                        fit_steps=fit_steps, fit_batch_rays=fit_batch_rays,
                        machinery=machinery, device=device, threads=threads,
                        overwrite=overwrite)
    rep = run_bench(opts)
    print()
    print(compare_markdown(list(rep["results"].values())), end="")
    print(f"wrote {out / 'README.md'} ({rep['total_seconds']:.0f} s)")
