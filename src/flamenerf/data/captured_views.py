"""Where the capture looked from: the training frames' camera centres (and head twists,
which place them relative to the head), for rendering colour at new cameras as the capture
saw it.

A radiance field's colour depends on the view direction, but the training frames constrain
it only for the directions they were filmed from; for a camera outside that range the
direction's encoding extrapolates, and on the built-in scene the face turned pale and the
lips lost their red there (docs/presets.md, "Less view dependence"). A renderer that asks
for the colour as seen from the nearest captured view instead
(`FlameNeRF.set_captured_views`) keeps what was filmed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flamenerf.data.dataset import Dataset, reference_position
from flamenerf.data.head_pose import canonical_vertices, head_twists


MAX_ANGLE_DEG = 2.0
"""How far (degrees) a ray's direction may stray from the nearest captured view before it is
turned back: within it, interpolation between captured views is left as the field learnt
it (the real clips' held-out frames, 0.1-1.6 degrees from their nearest captured view,
render as without the limit); beyond it, direction-dependent colour would extrapolate."""


@dataclass
class CapturedViews:
    """world (N, 3): the training frames' camera centres; twists (N, 6) or None: the frames'
    head twists ξ_f (data/head_pose.head_twists: exp(ξ_f) takes frame f's world to the
    head's canonical frame, so exp(ξ_f) c_f is where its camera saw the head from; None
    without head poses); focus (3,): the reference frame's face centre in the canonical
    frame (the point whose view picks a ray's captured camera)."""

    world: np.ndarray
    twists: np.ndarray | None
    focus: np.ndarray


def captured_views(ds: Dataset) -> CapturedViews:
    """The training frames' views of `ds` (float32)."""
    frames = ds.training_frames()
    world = np.stack([f.c2w[:3, 3] for f in frames]).astype(np.float32)
    ref = ds.frames[reference_position(ds)]
    focus = canonical_vertices(ds, [ref])[0].mean(0)
    return CapturedViews(world, head_twists(ds, frames), np.asarray(focus, np.float32))
