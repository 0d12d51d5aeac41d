"""The spatial prior's mask for any viewer camera: frame 0's face mesh rasterised into it."""

from __future__ import annotations

import threading

import numpy as np

from flamenerf.data.dataset import Dataset, Intrinsics
from flamenerf.tracking.silhouette import rasterize_silhouette


def estimate_dilation(ds: Dataset, position: int, max_px: int = 12) -> int:
    """Pixels (at the dataset's resolution) by which the dataset's stored masks grow the
    raw mesh silhouette, found by matching frame `position`'s stored mask; 0 when the
    mask cannot be read."""
    try:
        stored = ds.load_mask(ds.frames[position])
    except Exception:  # noqa: BLE001 - a missing mask only costs the estimate
        return 0
    from scipy import ndimage

    fr = ds.frames[position]
    raw = rasterize_silhouette(ds.face_vertices[position], ds.faces, ds.intrinsics, fr.c2w, 0)
    best, best_err = 0, int(np.count_nonzero(raw != stored))
    cur = raw
    for k in range(1, max_px + 1):
        cur = ndimage.binary_dilation(cur)
        err = int(np.count_nonzero(cur != stored))
        if err < best_err:
            best, best_err = k, err
        elif err > best_err:
            break
    return best


class FaceMasker:
    """Rasterises frame 0's face mesh for a camera; grows it as the dataset's masks were
    grown (scaled to the render's resolution). Remembers the last few results."""

    def __init__(self, ds: Dataset, position: int, dilate_px: int | None = None):
        self.vertices = np.asarray(ds.face_vertices[position], np.float64)
        self.faces = np.asarray(ds.faces)
        self.ref_height = ds.intrinsics.h
        self.dilate_px = estimate_dilation(ds, position) if dilate_px is None else dilate_px
        self._cache: dict[tuple, np.ndarray] = {}
        self._lock = threading.Lock()

    def dilation_for(self, intr: Intrinsics) -> int:
        return int(round(self.dilate_px * intr.h / self.ref_height))

    def __call__(self, intr: Intrinsics, c2w: np.ndarray) -> np.ndarray:
        key = (intr.w, intr.h, round(intr.fy, 6), np.round(c2w, 7).tobytes())
        with self._lock:
            hit = self._cache.get(key)
        if hit is not None:
            return hit
        m = rasterize_silhouette(self.vertices, self.faces, intr, c2w, self.dilation_for(intr))
        with self._lock:
            if len(self._cache) > 8:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = m
        return m
