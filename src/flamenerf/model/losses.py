"""The loss terms of FlameNeRF (`FlameNeRF.get_loss_dict` composes them) and what a
training step hands the model for them."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor


@dataclass
class LossBatch:
    """What a step's loss needs besides the forward pass's outputs (the trainer samples
    it from the dataset)."""

    rgb: Tensor
    """(R, 3) the rays' target colours."""
    mesh_depth: Tensor | None = None
    """(R,) the tracked face mesh's z-depth along each ray (inf where a ray misses the
    face), or None: no face-depth prior this step."""
    reg_points: Tensor | None = None
    """(P, 3) normalised points the face-region regulariser holds still
    (`FlameNeRF.face_reg_points`), or None: no regulariser this step."""
    reg_codes: Tensor | None = None
    """(P, code_dim) the ω of each point's frame."""
    moving: Tensor | None = None
    """(R,) the share in [0, 1] of each ray's pixel that is background moving by itself
    (the dataset's `moving_path` masks at the training resolution), or None: nothing is
    known to move (no per-ray weights at all: the loss is the plain mean)."""


@dataclass(frozen=True)
class LossWeights:
    """The loss terms' weights (TrainConfig's `interlevel_weight`, `face_depth_weight`,
    `face_depth_margin`, `face_reg_weight`, `moving_weight`)."""

    interlevel: float = 1.0
    face_depth: float = 0.0
    face_depth_margin: float = 0.01
    face_reg: float = 0.0
    moving: float = 1.0
    """A moving pixel's weight in the photometric terms (1: as any other)."""


PER_POINT = frozenset({"face_reg"})
"""Terms that average over the regulariser's points rather than over rays: a step split
into shards weighs them by each shard's share of the points."""


@dataclass
class LossTerms:
    """`weighted`: each term with its weight, in the order they are summed (`photometric`
    = photo (+ photo_coarse) + interlevel_weight · interlevel, then `face_depth`,
    `face_reg`); `raw`: the unweighted values, for the logs."""

    weighted: dict[str, Tensor] = field(default_factory=dict)
    raw: dict[str, Tensor] = field(default_factory=dict)


def ray_weights(moving: Tensor | None, weight: float) -> Tensor | None:
    """Each ray's weight in the photometric terms: 1 − (1 − weight) · share, from the
    share (R,) of its pixel that moves by itself -> (R,), or None where `moving` is None
    (every ray 1)."""
    if moving is None:
        return None
    return 1.0 - (1.0 - weight) * moving


def photometric_loss(rgb: Tensor, target: Tensor, weight: Tensor | None = None) -> Tensor:
    """Mean squared error of colours rgb (R, 3) against target (R, 3); with `weight` (R,)
    each ray's error scaled by its weight, still divided by all R rays (not by the weights'
    sum): a ray that is not weighed down pulls exactly as without weights, and a shard's
    loss stays its share of the batch's. -> scalar."""
    err = (rgb - target) ** 2
    return torch.mean(err) if weight is None else torch.mean(err * weight[:, None])


def still_depth(depth: Tensor, moving: Tensor | None) -> Tensor:
    """The mesh's depths (R,) with the rays through moving background made inf, which the
    face-depth prior skips: what moves in front of the face is not at the mesh's depth.
    -> (R,), `depth` itself where `moving` is None."""
    if moving is None:
        return depth
    return torch.where(moving > 0, torch.full_like(depth, math.inf), depth)


def face_region_loss(warped: Tensor, points: Tensor) -> Tensor:
    """Face-region regularisation: mean ‖D(x_3DMM; ω_i) − x_3DMM‖ over points (N, 3) sampled
    on each frame's face mesh — the warp must leave the face model where it is."""
    return torch.linalg.vector_norm(warped - points, dim=-1).mean()


def face_depth_loss(weights: Tensor, t: Tensor, depth: Tensor, margin: float) -> Tensor:
    """How far each ray's rendering weight lies from the face mesh, beyond `margin`:
    mean over the rays with a mesh depth of Σ_i w_i max(|t_i − d| − margin, 0). Without
    it `fast` renders the face as a fog centred centimetres behind the surface, which the
    captured views (and per-frame warps) accept and new cameras do not.

    weights (R, S), t (R, S) the samples' z-depths, depth (R,) the mesh's z-depth (inf: the
    ray misses the mesh; those rays do not count) -> scalar (0 when no ray has a depth).
    """
    hit = torch.isfinite(depth)
    if not bool(hit.any()):
        return weights.new_zeros(())
    off = ((t[hit] - depth[hit, None]).abs() - margin).clamp_min(0.0)
    return (weights[hit] * off).sum(-1).mean()


def psnr_from_mse(mse: float) -> float:
    return -10.0 * math.log10(max(mse, 1e-12))
