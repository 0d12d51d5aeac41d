"""The spatial prior's mask for a viewer camera and the slider expression: the silhouette
of that expression's face mesh (data/prior.py), remembered for the last few views."""

from __future__ import annotations

import threading

import numpy as np

from flamenerf.data.dataset import Dataset, Intrinsics
from flamenerf.data.prior import dataset_dilation, mesh_function, prior_mask
from flamenerf.rendering.filmed import FilmedFrame
from flamenerf.data.head_pose import posed_vertices


class FaceMasker:
    """masker(intr, c2w, expression, head, filmed) -> (H, W) bool: the prior's mask
    exactly as render and eval make it. Without an expression, the reference frame's own
    mesh is used; `head` (4, 4) canonical-from-world poses the mesh (None: frame 0's pose,
    or the filmed frame's own); `filmed` (rendering/filmed.FilmedFrame): that frame's
    tracked mesh, moved to the expression, as `render --split capture` makes it."""

    def __init__(self, ds: Dataset, position: int, model=None, dilate_px: int | None = None):
        self.ds = ds
        self.vertices = np.asarray(ds.face_vertices[position], np.float64)
        self.mesh_of = mesh_function(model, ds)
        self.dilate_px = dataset_dilation(ds) if dilate_px is None else dilate_px
        self._cache: dict[tuple, np.ndarray] = {}
        self._lock = threading.Lock()

    def __call__(self, intr: Intrinsics, c2w: np.ndarray,
                 expression: np.ndarray | None = None, head: np.ndarray | None = None,
                 filmed: FilmedFrame | None = None) -> np.ndarray:
        e = None if expression is None else np.asarray(expression, np.float32)
        key = (intr.w, intr.h, round(intr.fy, 6), np.round(c2w, 7).tobytes(),
               None if e is None else np.round(e, 4).tobytes(),
               None if head is None else np.round(head, 7).tobytes(),
               None if filmed is None else (filmed.canonical.tobytes(),
                                            filmed.expression.tobytes(),
                                            None if filmed.head is None
                                            else filmed.head.tobytes()))
        with self._lock:
            hit = self._cache.get(key)
        if hit is not None:
            return hit
        if filmed is not None:
            verts = filmed.mesh(self.mesh_of, filmed.expression if e is None else e, head)
        else:
            verts = posed_vertices(self.vertices if e is None else self.mesh_of(e), head)
        m = prior_mask(self.ds, verts, c2w, intr, self.dilate_px)
        with self._lock:
            if len(self._cache) > 8:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = m
        return m
