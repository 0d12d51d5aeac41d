"""`flamenerf export`."""

from __future__ import annotations

# what the command runs is imported inside its function: the CLI imports every command
# module to build its --help (cli.py), which stays quick that way

from pathlib import Path
from typing import Annotated

import numpy as np
import tyro


def export(
    run: Annotated[Path, tyro.conf.Positional],
    web: Path,
    track: Path | None = None,
    views: int = 24,
    overwrite: bool = False,
) -> None:
    """Export a trained run as a web page that plays it in any browser: orbit and zoom
    with the mouse, a slider per expression control, a track to play.

    The page draws the run's bake (RUN/baked.npz; made first, as `flamenerf bake` does, if
    the run has none) with WebGL2: index.html, player.js and avatar.js in one folder, opened
    from disk or any static web server, with no network and no Python. The head stays at
    frame 0's pose. See docs/rendering.md.

    Args:
        run: Trained run directory.
        web: Folder to write the page into (new or empty).
        track: Expressions for the page's Play button: a `flamenerf track` JSON file, an
            expression file or an ARKit take (Live Link Face CSV), mapped onto the run's
            controls.
        views: Views to bake from when the run has no bake yet.
        overwrite: Replace an earlier export in the folder.

    Example: flamenerf export runs/fast --web site/ --track take.csv
    """
    from flamenerf.splats.avatar import load_avatar
    from flamenerf.viewer.web_export import check_web_folder, export_web
    from flamenerf.workflows.bake import BakeOptions, bake

    check_web_folder(web, overwrite)
    baked = run / "baked.npz"
    if not baked.is_file():
        print(bake(BakeOptions(run, views=views)).describe())
    avatar = load_avatar(baked)
    frames = None
    if track is not None:
        from flamenerf.viewer.tracks import load_track_file

        t = load_track_file(track, avatar.names)
        frames = (np.clip(t.frames, avatar.low, avatar.high), t.fps)
    print(export_web(avatar, web, frames, overwrite).describe())
