"""The spatial prior's mask 𝕀: the face mesh's silhouette, for any camera, resolution and
expression. The one place masks are made: datasets (synth, preprocess), training
(`training_mask`), evaluation, rendering and the viewer all call it, so the model always
sees the prior it was trained with.

A mask is the mesh rasterised at the *dataset's* pixel density (the target camera scaled so
that its height is the dataset's), grown by the dataset's dilation (pixels at that density,
stored in transforms.json as `prior.dilation_px` by the dataset writer), then area-resized
to the target resolution and thresholded at 0.5 — exactly how training masks are made from
the dataset's stored ones.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from flamenerf.data.dataset import Dataset, Intrinsics, reference_position
from flamenerf.data.mesh_depth import triangle_ids
from flamenerf.data.mesh_model import fit_dataset_expression_model
from flamenerf.images import resize_image
from flamenerf.meshes import expression_mesh


def rasterize_silhouette(vertices: np.ndarray, faces: np.ndarray, intr: Intrinsics,
                         c2w: np.ndarray, dilate_px: int = 0) -> np.ndarray:
    """Pixels covered by any front-of-camera triangle of the mesh.

    vertices (V, 3) world; faces (F, 3) int; -> (H, W) bool, grown by `dilate_px` pixels so
    that the prior also covers the mesh's near surroundings.
    """
    from scipy import ndimage

    mask = triangle_ids(vertices, faces, intr, c2w, intr.w, intr.h) >= 0
    if dilate_px > 0:
        mask = ndimage.binary_dilation(mask, iterations=int(dilate_px))
    return mask


def training_mask(mask: np.ndarray, w: int, h: int) -> np.ndarray:
    """A mask at another resolution: area average, then > 0.5. (H, W) bool -> (h, w) bool."""
    if mask.shape == (h, w):
        return np.asarray(mask, bool)
    return resize_image(np.asarray(mask, np.float32)[..., None], w, h)[..., 0] > 0.5


def estimate_dilation(ds: Dataset, position: int | None = None, max_px: int = 12) -> int:
    """For datasets written before the dilation was stored: the dilation (dataset pixels)
    that best reproduces one frame's stored mask (default: the reference frame) from its
    mesh (highest IoU); 0 when the mask cannot be read or is empty."""
    from scipy import ndimage

    pos = reference_position(ds) if position is None else position
    fr = ds.frames[pos]
    try:
        target = ds.load_mask(fr)
    except Exception:  # noqa: BLE001 - a missing mask only costs the estimate
        return 0
    if not target.any():
        return 0
    m = rasterize_silhouette(ds.face_vertices[pos], ds.faces, ds.intrinsics, fr.c2w, 0)
    best, best_iou = 0, -1.0
    for px in range(max_px + 1):
        if px > 0:
            m = ndimage.binary_dilation(m)
        iou = (m & target).sum() / max((m | target).sum(), 1)
        if iou > best_iou + 1e-9:
            best, best_iou = px, iou
    return best


def dataset_dilation(ds: Dataset) -> int:
    """The dilation the dataset's masks were made with (transforms.json `prior.dilation_px`),
    estimated from a stored mask for older datasets."""
    stored = (ds.meta.get("prior") or {}).get("dilation_px")
    if isinstance(stored, (int, float)) and not isinstance(stored, bool) and stored >= 0:
        return int(stored)
    return estimate_dilation(ds)


def prior_mask(ds: Dataset, vertices: np.ndarray, c2w: np.ndarray, intr: Intrinsics,
               dilate_px: int | None = None, faces: np.ndarray | None = None) -> np.ndarray:
    """(H, W) bool mask at camera `intr`, `c2w` for the mesh `vertices` (see module doc).
    `dilate_px` in dataset pixels (default: the dataset's); `faces`: part of the mesh."""
    dil = dataset_dilation(ds) if dilate_px is None else int(dilate_px)
    dense = intr if intr.h == ds.intrinsics.h else intr.scaled(ds.intrinsics.h / intr.h)
    full = rasterize_silhouette(vertices, ds.faces if faces is None else faces, dense, c2w, dil)
    return training_mask(full, intr.w, intr.h)


def mesh_function(model, ds: Dataset) -> Callable[[np.ndarray], np.ndarray]:
    """β (E,) -> the face mesh (V, 3) of that expression: the run's own expression model
    (mesh-guided runs carry it), else one fitted on the dataset's training frames. The
    prior of a driven expression is this mesh's silhouette, so a jaw opened below the
    reference frame's chin still gets β."""
    prior = getattr(model, "expression", None)
    if prior is not None and prior.uses_mesh_model:
        neutral, basis = prior.mesh_neutral.cpu(), prior.mesh_basis.cpu()
    else:
        neutral, basis = fit_dataset_expression_model(ds)

    def mesh_of(beta: np.ndarray) -> np.ndarray:
        return expression_mesh(neutral, basis, torch.as_tensor(np.asarray(beta, np.float32))
                               ).numpy()

    return mesh_of
