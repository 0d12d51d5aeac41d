"""`flamenerf bench`."""

from __future__ import annotations

# what the command runs is imported inside its function: the CLI imports every command
# module to build its --help (cli.py), which stays quick that way

from typing import Annotated

import tyro

from flamenerf.workflows.bench import BenchOptions


def bench(opts: Annotated[BenchOptions, tyro.conf.OmitArgPrefixes, tyro.conf.arg(name="")]
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
    """
    from flamenerf.errors import UserError
    from flamenerf.evaluation.report import compare_markdown
    from flamenerf.workflows.bench import run_bench

    for name, v in (("--scene-size", opts.scene_size), ("--frames", opts.frames),
                    ("--train-size", opts.train_size), ("--steps", opts.steps),
                    ("--batch-rays", opts.batch_rays), ("--fit-batch-rays", opts.fit_batch_rays)):
        if v is not None and v < 1:
            raise UserError(f"{name} {v}: must be at least 1")
    if opts.scene_size < 16:
        raise UserError(f"--scene-size {opts.scene_size}: must be at least 16")
    if opts.fit_steps is not None and opts.fit_steps < 0:
        raise UserError(f"--fit-steps {opts.fit_steps}: must be >= 0")
    if not 0 <= opts.seed < 2 ** 63:
        raise UserError(f"--seed {opts.seed}: must be in 0..2^63-1")
    # checked before the slow work: the report is written only at the end
    if opts.out.exists() and not opts.out.is_dir():
        raise UserError(f"--out {opts.out}: is a file, not a folder")
    rep = run_bench(opts)
    print()
    print(compare_markdown(list(rep["results"].values())), end="")
    print(f"wrote {opts.out / 'README.md'} ({rep['total_seconds']:.0f} s)")
