"""Image metrics on float images in [0, 1], the regions of a frame they are taken on (face,
face interior, beyond the head, the static scene), their means over frames, and the bar a
control's re-tracked response must meet (`RESPONDS`)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from flamenerf.geometry import project_points
from flamenerf.tracking.background import person_mask

if TYPE_CHECKING:  # for the annotation only: a FrameSet holds torch tensors
    from flamenerf.data.scene import FrameSet


def mse(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    d = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    if mask is not None:
        m = np.asarray(mask, bool)
        if not m.any():
            return float("nan")
        d = d[m]
    return float(d.mean())


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    m = mse(a, b, mask)
    return float("nan") if math.isnan(m) else -10.0 * math.log10(max(m, 1e-12))


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """Structural similarity of two (H, W, 3) images (scikit-image, Gaussian weights as in
    Wang et al. 2004)."""
    from skimage.metrics import structural_similarity

    return float(structural_similarity(np.asarray(a, np.float64), np.asarray(b, np.float64),
                                       channel_axis=-1, data_range=1.0, gaussian_weights=True,
                                       sigma=1.5, use_sample_covariance=False))


def mean_abs_change(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean absolute per-pixel difference on the 0-255 scale, over the pixels in `mask`
    (all channels): the background-leakage measure. NaN when the mask is empty."""
    d = np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)) * 255.0
    if mask is not None:
        m = np.asarray(mask, bool)
        if not m.any():
            return float("nan")
        d = d[m]
    return float(d.mean())


def scene_masks(fs: FrameSet) -> np.ndarray:
    """Where each frame of `fs` shows only the static scene: outside the generous region
    around the person that the camera solve masks out (an ellipse around the projected face
    mesh for the head and hair, a widening band below the chin for neck and shoulders;
    tracking.background.person_mask). "Background" (outside the face mask) also holds hair,
    neck and shoulders, which no rigid motion carries; the scene is what should register
    across frames. -> (N, H, W) bool."""
    out = []
    for i in range(fs.n):
        px, _ = project_points(fs.face_vertices[i].numpy().astype(np.float64), fs.intr,
                               fs.c2w[i].numpy().astype(np.float64))
        out.append(~person_mask(px, fs.intr.w, fs.intr.h))
    return np.stack(out)


def face_interior(face: np.ndarray) -> np.ndarray:
    """The face mask (H, W) bool without its outline: eroded by H/64 pixels (two at 128 px).
    The outline's pixels mix the face with what lies behind it, so at a new camera they
    also measure the background and the edge's sharpness, alike with and without β."""
    from scipy import ndimage

    return ndimage.binary_erosion(face, iterations=max(1, round(face.shape[0] / 64)))


BEYOND_HEAD = 0.08
"""Scene units (metres) behind the face interior's median true depth from which a face-mask
pixel shows what lies beyond the head (`beyond_head`)."""


def beyond_head(face: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Pixels of the face mask (H, W) bool whose ground-truth z-depth (H, W) lies more than
    `BEYOND_HEAD` behind the median depth of the face's interior: the room seen past the
    head's silhouette through the mask's dilation. At a new camera they measure how the
    background registers there, alike with and without β. -> (H, W) bool."""
    inner = face_interior(face)
    if not inner.any():
        return np.zeros_like(face)
    return face & (depth > np.median(depth[inner]) + BEYOND_HEAD)


def image_metrics(pred: np.ndarray, gt: np.ndarray, face: np.ndarray,
                  scene: np.ndarray | None = None) -> dict[str, float]:
    """pred, gt (H, W, 3) in [0, 1]; face (H, W) bool; scene (H, W) bool (`scene_masks`;
    None: no psnr_scene). `psnr_face_interior` / `psnr_face_outline`: the face without its
    outline (`face_interior`) / the outline alone."""
    m = mse(pred, gt)
    inner = face_interior(face)
    out = {"mse": m, "psnr": psnr(pred, gt), "ssim": ssim(pred, gt),
           "psnr_face": psnr(pred, gt, face),
           "psnr_face_interior": psnr(pred, gt, inner),
           "psnr_face_outline": psnr(pred, gt, face & ~inner),
           "psnr_background": psnr(pred, gt, ~face)}
    if scene is not None:
        out["psnr_scene"] = psnr(pred, gt, scene)
    return out


SUMMARY_KEYS = ("mse", "psnr", "ssim", "psnr_face", "psnr_face_interior", "psnr_face_outline",
                "psnr_background", "psnr_scene")


def summarize(per_frame: list[dict[str, Any]], keys=SUMMARY_KEYS) -> dict[str, Any]:
    """Means over frames (frames where a value is NaN, e.g. no face pixels, are skipped)."""
    out: dict[str, Any] = {"num_frames": len(per_frame)}
    for k in keys:
        v = np.array([f.get(k, np.nan) for f in per_frame], np.float64)
        v = v[np.isfinite(v)]
        out[k] = float(v.mean()) if v.size else float("nan")
    return out


RESPONDS = (0.5, 0.9)
"""The bar for a control that responds: re-tracked gain at least 0.5 and correlation
at least 0.9."""

GEOMETRY_FOLLOWS = (0.9, 0.02)
"""A sweep moves the face as commanded by geometry when its measure correlates at least
this well with the command, the right way, and changes by at least this much of the eye
distance over the sweep (a fraction of a pixel at 128 px is tracker jitter)."""


def responds(gain: float, correlation: float) -> bool:
    """Whether a control's (gain, correlation) meets `RESPONDS` (NaN does not)."""
    return bool(gain >= RESPONDS[0] and correlation >= RESPONDS[1])
