"""Face-model silhouettes: the spatial prior's mask, made by rasterising the face mesh."""

from __future__ import annotations

import numpy as np
from PIL import Image, ImageDraw
from scipy import ndimage

from flamenerf.data.dataset import Intrinsics
from flamenerf.geometry import project_points


def rasterize_silhouette(
    vertices: np.ndarray,
    faces: np.ndarray,
    intr: Intrinsics,
    c2w: np.ndarray,
    dilate_px: int = 0,
) -> np.ndarray:
    """Pixels covered by any front-of-camera triangle of the mesh.

    vertices (V, 3) world; faces (F, 3) int; -> (H, W) bool. `dilate_px` grows the mask
    by that many pixels so that the prior also covers the mesh's near surroundings.
    """
    uv, z = project_points(np.asarray(vertices, np.float64), intr, c2w)
    img = Image.new("L", (intr.w, intr.h), 0)
    draw = ImageDraw.Draw(img)
    tri_ok = (z[faces] > 1e-6).all(axis=1)
    for tri in faces[tri_ok]:
        draw.polygon([tuple(p) for p in uv[tri]], fill=255)
    mask = np.asarray(img) > 0
    if dilate_px > 0:
        mask = ndimage.binary_dilation(mask, iterations=int(dilate_px))
    return mask
