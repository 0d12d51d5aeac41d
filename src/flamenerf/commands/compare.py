"""`flamenerf compare`."""

from __future__ import annotations

# what the command runs is imported inside its function: the CLI imports every command
# module to build its --help (cli.py), which stays quick that way

from pathlib import Path
from typing import Annotated

import tyro


def compare(
    runs: Annotated[list[Path], tyro.conf.Positional],
    labels: list[str] | None = None,
    out: Path | None = None,
    latex: bool = False,
    overwrite: bool = False,
) -> None:
    """Compare evaluated runs side by side, in the layout of the paper's Table 1.

    Reads each RUN/eval/metrics.json (written by `flamenerf eval`) and prints one table:
    Method, the paper's held-out MSE and PSNR, then SSIM, PSNR inside/outside the face,
    re-animation PSNR/SSIM and background leakage where measured; the best value of each
    column is bold. Method names come from each run's expression mode (FLAME-in-NeRF,
    Nerfies, No prior) unless --labels are given.

    Example: flamenerf compare runs/fast runs/nerfies runs/no-prior --out table.md

    Args:
        runs: Run directories (or metrics.json files).
        labels: One label per run, replacing the method names.
        out: Also write the table to this file (Markdown, or LaTeX with --latex).
        latex: Print a LaTeX (booktabs) table instead of Markdown.
        overwrite: Replace --out if it exists.
    """
    from flamenerf.errors import UserError
    from flamenerf.evaluation.report import compare_latex, compare_markdown, load_eval
    from flamenerf.io import atomic_write_text

    if not runs:
        raise UserError("give at least one run directory")
    if labels is not None and len(labels) != len(runs):
        raise UserError(f"--labels: got {len(labels)} labels for {len(runs)} runs")
    if out is not None and out.is_dir():
        raise UserError(f"--out {out}: is a folder; give a file name")
    if out is not None and out.exists() and not overwrite:
        raise UserError(f"{out}: already exists (pass --overwrite to replace it)")
    if out is not None:  # before the table is printed, not after
        from flamenerf.outdir import writable_dir

        writable_dir(out.parent, "table")
    results = [load_eval(r) for r in runs]
    table = (compare_latex if latex else compare_markdown)(results, labels)
    print(table, end="")
    if out is not None:
        atomic_write_text(out, table)
        print(f"wrote {out}")
