"""Cuts in a clip: where one shot ends and the next begins (an edited clip, a vlog's jump
cuts). The camera solve smooths the cameras' motion over time; across a cut that motion is
not continuous, and smoothing it pulled the frames on either side off their landmarks (on a
test clip with one cut, three frames were dropped as misfits). Found from the frames'
thumbnails: a cut changes the picture more than any motion between two frames."""

from __future__ import annotations

import numpy as np
from PIL import Image

THUMB = 32
"""Side of the grey thumbnails compared, pixels."""

CUT_MIN = 0.08
"""A change between consecutive frames' thumbnails (mean absolute difference, grey levels in
[0, 1]) is a cut only above this: within the shared clips' shots, at 10 of their 30 frames
a second (a moving camera; strong expressions and head turns), at most 0.045."""

CUT_RATIO = 8.0
"""... and above this many times the clip's median change (a clip of little motion)."""


def thumbnail(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 -> (THUMB, THUMB) float32 grey in [0, 1] (area-averaged)."""
    img = Image.fromarray(np.ascontiguousarray(rgb[..., :3])).convert("L")
    return np.asarray(img.resize((THUMB, THUMB), Image.Resampling.BOX), np.float32) / 255.0


def shot_indices(thumbs: np.ndarray) -> np.ndarray:
    """Thumbnails (S, h, w) of a clip's frames in order -> the shot of each frame (S,)
    int64, 0 for the first, one more after each cut."""
    thumbs = np.asarray(thumbs, np.float32)
    if len(thumbs) < 2:
        return np.zeros(len(thumbs), np.int64)
    change = np.abs(thumbs[1:] - thumbs[:-1]).mean(axis=(1, 2))
    cut = change > max(CUT_MIN, CUT_RATIO * float(np.median(change)))
    return np.concatenate([[0], np.cumsum(cut)]).astype(np.int64)
