"""The subject's linear β -> face mesh model fitted on a dataset's training frames, and how
far it misses them. The spatial prior (data/prior.mesh_function) and the mesh guide
(training) both take it."""

from __future__ import annotations

import numpy as np
import torch

from flamenerf.data.dataset import Dataset, Frame
from flamenerf.data.face_parts import control_weights, has_parts
from flamenerf.data.generic_shapes import generic_basis, uncovered
from flamenerf.data.head_pose import canonical_vertices
from flamenerf.meshes import expression_mesh, fit_expression_model


def fit_dataset_expression_model(ds: Dataset, ridge: float = 1e-3, face_parts: bool = True,
                                 stored: bool = True, generic: bool = False
                                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """The subject's linear β -> mesh model fitted on the training frames' face meshes, in
    the canonical frame (the head at frame 0's pose; the world without head poses); with
    `face_parts`, each named control moves only its part of the face where the dataset's
    controls and mesh say which (data/face_parts.py). With `stored`, the model the dataset
    carries (`Dataset.mesh_model`) where it was fitted with the same ridge and face parts.
    With `generic`, the eye and brow controls the training frames leave still take their
    generic shapes (`generic_controls`; data/generic_shapes.py).
    -> neutral (V, 3), basis (E, V, 3) in world units."""
    kept = ds.mesh_model
    if stored and face_parts and kept is not None and np.isclose(kept.ridge, ridge):
        neutral, basis = torch.from_numpy(kept.neutral.copy()), torch.from_numpy(kept.basis.copy())
    else:
        neutral, basis = _fit(ds, ridge, face_parts)
    fill = generic_controls(ds) if generic else []
    if fill:
        shapes = generic_basis(ds.expression_kind, ds.expression_names, neutral.numpy(),
                               ds.face_landmarks)
        basis[fill] = torch.from_numpy(shapes[fill])
    return neutral, basis


def generic_controls(ds: Dataset) -> list[int]:
    """The controls of `ds` that a generic shape stands in for (data/generic_shapes.py): eye
    and brow controls its training frames leave (nearly) still; none where its face's parts
    are unknown."""
    if not has_parts(ds.expression_kind, ds.expression_names, ds.face_vertices.shape[1],
                     ds.face_landmarks):
        return []
    return uncovered(ds.expression_names, ds.expression_matrix(ds.training_frames()))


def _fit(ds: Dataset, ridge: float, face_parts: bool) -> tuple[torch.Tensor, torch.Tensor]:
    train = ds.training_frames()
    verts = canonical_vertices(ds, train)
    weights = (control_weights(ds.expression_kind, ds.expression_names, verts.mean(0),
                               ds.face_landmarks) if face_parts else None)
    return fit_expression_model(torch.from_numpy(ds.expression_matrix(train)),
                                torch.from_numpy(verts), ridge,
                                None if weights is None else torch.from_numpy(weights))


def expression_model_residual(ds: Dataset, neutral: torch.Tensor, basis: torch.Tensor,
                              frames: list[Frame] | None = None) -> torch.Tensor:
    """How far the β -> mesh model (`fit_dataset_expression_model`'s neutral (V, 3), basis
    (E, V, 3)) misses each vertex of the frames' meshes (default: the training frames): RMS
    over the frames, world units. -> (V,)"""
    frames = ds.training_frames() if frames is None else frames
    verts = torch.from_numpy(canonical_vertices(ds, frames)).double()
    fit = expression_mesh(neutral.double(), basis.double(),
                          torch.from_numpy(ds.expression_matrix(frames)).double())
    return (fit - verts).norm(dim=-1).pow(2).mean(0).sqrt().float()
