"""Background that moves by itself (leaves in the wind, water, people walking past): where
the background's dense optical flow between consecutive frames disagrees with what the
camera model predicts for a static scene.

    consecutive frames -> dense flow (OpenCV's DIS) -> distance of each flow's end point to
    where the camera model puts it (a rotation: one point; SfM: the epipolar line; a still
    camera: the start) -> large, on texture, outside the person -> cleaned (opening,
    closing, a vote over neighbouring frames)

Flow is only trusted where the image has texture (the smaller eigenvalue of its structure
tensor): on a plain wall it drifts with noise and would flag a still background. Motion
along an epipolar line is invisible to the SfM model's test, a known limit of two-view
checks; swaying is rarely only that.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

PairResidual = Callable[[int, int, np.ndarray, np.ndarray], np.ndarray]
"""(frame a, frame b, points in a (P, 2), their flow's end points in b (P, 2)) -> (P,)
distance of each end point to the static scene's prediction, in the frames' pixels."""


@dataclass
class MovingOptions:
    side: int = 320
    """Flow is computed on frames resized to this many pixels on their long side (smaller
    ones upsampled: the flow needs a few pixels of texture either side)."""
    threshold_px: float = 1.5
    """A flow end point this far (pixels of the matched frames, as the camera model sees
    them) or further from the static prediction moves by itself..."""
    threshold_mads: float = 4.0
    """... and further than this many robust deviations of the background's residuals
    (the camera model's own misfit, rolling shutter, flow noise)."""
    min_texture: float = 2e-4
    """Flow counts only where the structure tensor's smaller eigenvalue (OpenCV's
    cornerMinEigenVal on 0-1 grey, 5 px window) exceeds this."""
    min_region: float = 0.002
    """Flagged regions smaller than this share of the frame are dropped as noise."""
    vote: int = 2
    """A pixel moves in a frame when flagged there or in enough of the two neighbouring
    frames: at least `vote` of the three."""


def detect_moving(frames: np.ndarray, background: np.ndarray, residual: PairResidual,
                  scale: float, opts: MovingOptions | None = None) -> np.ndarray:
    """frames (N, H, W) uint8 grey, background (N, H, W) bool (outside the person), both at
    the resolution `residual` works in times `scale` (<= 1: they may be downscaled);
    -> (N, H, W) bool, background that moves by itself in each frame."""
    opts = opts or MovingOptions()
    n, h, w = frames.shape
    if n < 2:
        return np.zeros_like(background)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    grid = np.stack([xx, yy], -1) + 0.5  # pixel centres, as COLMAP counts them
    raw = np.zeros((n, h, w), bool)
    for k in range(n):
        texture = cv2.cornerMinEigenVal(frames[k].astype(np.float32) / 255, 5) > opts.min_texture
        use = background[k] & texture
        if not use.any():
            continue
        # against both neighbours: a sway slows to a stop and turns, so one pair of frames
        # may see it still where the other does not
        for b in (k - 1, k + 1):
            if 0 <= b < n:
                raw[k] |= _flagged(dis.calc(frames[k], frames[b], None), use, grid, k, b,
                                   residual, scale, opts)
    return _clean(raw, background, opts)


def _flagged(flow: np.ndarray, use: np.ndarray, grid: np.ndarray, a: int, b: int,
             residual: PairResidual, scale: float, opts: MovingOptions) -> np.ndarray:
    """Pixels `use` (H, W) of frame a whose flow (H, W, 2) to frame b the static scene
    does not explain: -> (H, W) bool."""
    x0 = grid[use] / scale
    e = residual(a, b, x0, (grid[use] + flow[use]) / scale)
    ok = np.isfinite(e)
    flag = np.zeros(use.shape, bool)
    if ok.any():
        med = float(np.median(e[ok]))
        mad = 1.4826 * float(np.median(np.abs(e[ok] - med)))
        flag[use] = ok & (e > max(opts.threshold_px, med + opts.threshold_mads * mad))
    return flag


def _clean(raw: np.ndarray, background: np.ndarray, opts: MovingOptions) -> np.ndarray:
    """Speckles removed (opening), regions filled (closing), small ones dropped, then the
    vote over each frame and its two neighbours; never on the person."""
    n, h, w = raw.shape
    r = max(1, round(0.01 * max(h, w)))
    k_open = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    k_close = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (6 * r + 1, 6 * r + 1))
    min_px = opts.min_region * h * w
    out = np.zeros_like(raw)
    for k in range(n):
        m = cv2.morphologyEx(raw[k].astype(np.uint8), cv2.MORPH_OPEN, k_open)
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, k_close)
        count, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
        big = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] >= min_px)
        big = big[big > 0]
        out[k] = np.isin(labels, big)
    votes = out.astype(np.int8)
    votes[1:] += out[:-1]
    votes[:-1] += out[1:]
    return (votes >= min(opts.vote, n)) & background
