"""The viewer's options: a module of its own so that `flamenerf --help` does not import the
viewer (torch, viser)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro


@dataclass
class ViewerOptions:
    """Options of `flamenerf view` (its flags, same names; the help text below is their
    --help).

    Attributes:
        port: TCP port to serve on.
        host: Address to listen on (default: this machine only).
        track: Expression track JSON from `flamenerf track`, or an ARKit take (Live Link
            Face CSV), played at its rate (repeat for several).
        resolution: Height in pixels of the refined image (0: the run's training height).
        max_resolution: Upper end of the resolution slider.
        progressive: Render coarse first while the view changes, refine when still.
        dataset: Dataset to read cameras, face mesh and tracks from (default: the run's).
        settle_s: Seconds the view must stay still before the refined image (not a flag).
        verbose: Log viser's server messages (not a flag).
    """

    port: int = 8080
    host: str = "127.0.0.1"
    track: Annotated[tuple[Path, ...], tyro.conf.UseAppendAction] = ()
    resolution: int = 0
    max_resolution: int = 1024
    progressive: bool = True
    dataset: Path | None = None
    settle_s: Annotated[float, tyro.conf.Suppress] = 0.25
    verbose: Annotated[bool, tyro.conf.Suppress] = False
