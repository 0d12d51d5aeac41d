"""Loss terms."""

from __future__ import annotations

import math

import torch
from torch import Tensor


def face_region_loss(warped: Tensor, points: Tensor) -> Tensor:
    """Face-region regularisation: mean ‖D(x_3DMM; ω_i) − x_3DMM‖ over points (N, 3) sampled
    on each frame's face mesh — the warp must leave the face model where it is."""
    return torch.linalg.vector_norm(warped - points, dim=-1).mean()


def psnr_from_mse(mse: float) -> float:
    return -10.0 * math.log10(max(mse, 1e-12))
