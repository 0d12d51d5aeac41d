"""`flamenerf bake`."""

from __future__ import annotations

# what the command runs is imported inside its function: the CLI imports every command
# module to build its --help (cli.py), which stays quick that way

from typing import Annotated

import tyro

from flamenerf.workflows.bake import BakeOptions


def bake(opts: Annotated[BakeOptions, tyro.conf.OmitArgPrefixes, tyro.conf.arg(name="")]
         ) -> None:
    """Bake a trained run into splats that follow its expression controls, for
    `render --baked` and `export --web`.

    The run renders frame 0's codes from a set of views (frame 0's camera, the capture's
    cameras and the render's orbit and spiral paths), at the reference expression and with
    each control moved alone to the end of its training range; each pixel the splats do
    not already show becomes a splat, and the face's splats (inside the spatial prior's
    silhouette, near the face mesh) get a linear offset of position and colour per control.
    Nothing else moves with the expression. The head stays at frame 0's pose. Writes
    RUN/baked.npz (--out to choose). See docs/rendering.md.

    Example: flamenerf bake runs/fast && flamenerf render runs/fast --baked --camera orbit
    """
    from flamenerf.workflows.bake import bake as run_bake

    print(run_bake(opts).describe())
