"""The spatial prior's mask 𝕀 for any camera and expression: the face mesh's silhouette.

Training masks are the dataset's silhouettes (rasterised by `synth`/`preprocess` with a
small dilation at the dataset resolution) resized to the training resolution with an
area filter and a 0.5 threshold (`FrameSet`). Masks for novel cameras are made the same
way: rasterise the mesh at the dataset resolution with the dataset's dilation (estimated
from frame 0 when not given), then resize, so that the model sees the prior it was
trained with.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from flamenerf.data.dataset import Dataset, Intrinsics, reference_position
from flamenerf.data.scene import fit_dataset_expression_model
from flamenerf.images import resize_image
from flamenerf.meshes import expression_mesh
from flamenerf.tracking.silhouette import rasterize_silhouette


def estimate_dilation(ds: Dataset, position: int | None = None, max_px: int = 8) -> int:
    """The dilation (pixels at the dataset resolution) that best reproduces the dataset's
    mask of one frame (default: frame 0) from its face mesh (highest IoU)."""
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
               dilate_px: int, faces: np.ndarray | None = None) -> np.ndarray:
    """(H, W) bool mask at `intr` for one camera: rasterised at the dataset resolution with
    `dilate_px`, then resized like the training masks. `faces`: a part of the mesh (default:
    all of it)."""
    full = rasterize_silhouette(vertices, ds.faces if faces is None else faces,
                                ds.intrinsics, c2w, dilate_px)
    if (intr.w, intr.h) == (ds.intrinsics.w, ds.intrinsics.h):
        return full
    return resize_image(full[..., None].astype(np.float32), intr.w, intr.h)[..., 0] > 0.5


def mesh_function(model, ds: Dataset) -> Callable[[np.ndarray], np.ndarray]:
    """β (E,) -> the face mesh (V, 3) of that expression: the run's own expression model
    (mesh-guided runs carry it), else one fitted on the dataset's training frames. The
    spatial prior of a driven expression is this mesh's silhouette, so a jaw opened below
    the reference frame's chin still gets β."""
    if getattr(model, "mesh_guided", False):
        neutral, basis = model.mesh_neutral.cpu(), model.mesh_basis.cpu()
    else:
        neutral, basis = fit_dataset_expression_model(ds)

    def mesh_of(beta: np.ndarray) -> np.ndarray:
        b = torch.as_tensor(np.asarray(beta, np.float32))
        return expression_mesh(neutral, basis, b).numpy()

    return mesh_of


def dataset_scaled(ds: Dataset, intr: Intrinsics) -> bool:
    """Whether `intr` is the dataset's camera at another resolution (same field of view),
    which `prior_mask` needs (it rasterises with the dataset's intrinsics)."""
    d = ds.intrinsics
    return (abs(intr.fx / intr.w - d.fx / d.w) < 1e-6 * d.fx / d.w
            and abs(intr.cx / intr.w - d.cx / d.w) < 1e-6 and
            abs(intr.cy / intr.h - d.cy / d.h) < 1e-6)
