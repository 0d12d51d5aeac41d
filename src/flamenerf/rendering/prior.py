"""The spatial prior's mask 𝕀 for any camera and expression: the face mesh's silhouette.

Training masks are the dataset's silhouettes (rasterised by `synth`/`preprocess` with a
small dilation at the dataset resolution) resized to the training resolution with an
area filter and a 0.5 threshold (`FrameSet`). Masks for novel cameras are made the same
way: rasterise the mesh at the dataset resolution with the dataset's dilation (estimated
from frame 0 when not given), then resize, so that the model sees the prior it was
trained with.
"""

from __future__ import annotations

import numpy as np

from flamenerf.data.dataset import Dataset, Intrinsics
from flamenerf.data.scene import resize_image
from flamenerf.tracking.silhouette import rasterize_silhouette


def estimate_dilation(ds: Dataset, position: int | None = None, max_px: int = 8) -> int:
    """The dilation (pixels at the dataset resolution) that best reproduces the dataset's
    mask of one frame (default: frame 0) from its face mesh (highest IoU)."""
    from flamenerf.rendering.cameras import reference_position

    pos = reference_position(ds) if position is None else position
    fr = ds.frames[pos]
    target = ds.load_mask(fr)
    base = rasterize_silhouette(ds.face_vertices[pos], ds.faces, ds.intrinsics, fr.c2w, 0)
    if not target.any():
        return 0
    from scipy import ndimage

    best, best_iou, m = 0, -1.0, base
    for px in range(max_px + 1):
        if px > 0:
            m = ndimage.binary_dilation(m)
        iou = (m & target).sum() / max((m | target).sum(), 1)
        if iou > best_iou + 1e-9:
            best, best_iou = px, iou
    return best


def prior_mask(ds: Dataset, vertices: np.ndarray, c2w: np.ndarray, intr: Intrinsics,
               dilate_px: int) -> np.ndarray:
    """(H, W) bool mask at `intr` for one camera: rasterised at the dataset resolution with
    `dilate_px`, then resized like the training masks."""
    full = rasterize_silhouette(vertices, ds.faces, ds.intrinsics, c2w, dilate_px)
    if (intr.w, intr.h) == (ds.intrinsics.w, ds.intrinsics.h):
        return full
    return resize_image(full[..., None].astype(np.float32), intr.w, intr.h)[..., 0] > 0.5


def dataset_scaled(ds: Dataset, intr: Intrinsics) -> bool:
    """Whether `intr` is the dataset's camera at another resolution (same field of view),
    which `prior_mask` needs (it rasterises with the dataset's intrinsics)."""
    d = ds.intrinsics
    return (abs(intr.fx / intr.w - d.fx / d.w) < 1e-6 * d.fx / d.w
            and abs(intr.cx / intr.w - d.cx / d.w) < 1e-6 and
            abs(intr.cy / intr.h - d.cy / d.h) < 1e-6)
