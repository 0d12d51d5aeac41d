"""`flamenerf convert`."""

from __future__ import annotations

# what the command runs is imported inside its function: the CLI imports every command
# module to build its --help (cli.py), which stays quick that way

from pathlib import Path
from typing import Annotated

import tyro


def convert(
    run: Annotated[Path, tyro.conf.Positional],
    trust: bool = False,
) -> None:
    """Rewrite the checkpoints of a run made by flamenerf 0.1 in the safe format.

    Checkpoints now hold only tensors and plain values and load without pickle, so a
    shared run cannot run code on your machine. Older ones pickled Python objects, and
    loading them runs whatever they contain: convert a run only if you trust where it came
    from. See docs/reliability.md.

    Example: flamenerf convert runs/old --trust

    Args:
        run: Run directory (made by `flamenerf train`).
        trust: Confirm that you trust this run's source (loading it can run code).
    """
    from flamenerf.errors import UserError
    from flamenerf.training.checkpoint import checkpoints, convert_legacy

    if run.exists() and not run.is_dir():
        raise UserError(f"{run}: is a file; give the run directory made by `flamenerf train`")
    if not run.exists():
        raise UserError(f"{run}: run directory does not exist")
    cks = checkpoints(run)
    if not cks:
        raise UserError(f"{run}: no checkpoints in {run / 'checkpoints'}")
    if not trust:
        raise UserError(f"{run}: converting loads its checkpoints with pickle, which can run "
                        "any code they contain; pass --trust if you trust where it came from")
    done = [p for p in cks if convert_legacy(p)]
    print(f"converted {len(done)} of {len(cks)} checkpoint(s) in {run / 'checkpoints'}"
          + ("" if done else " (all were in the safe format already)"))
