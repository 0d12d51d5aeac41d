"""Loss terms."""

from __future__ import annotations

import math

import torch
from torch import Tensor


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
