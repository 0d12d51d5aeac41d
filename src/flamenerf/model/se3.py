"""SE(3) exponential maps for the Nerfies deformation field, batched over leading dims.

Equations from Lynch & Park, *Modern Robotics* (2017): Rodrigues' formula (3.51) and the
screw-motion exponential (3.88).
"""

from __future__ import annotations

import torch
from torch import Tensor

_EPS = 1e-8


def skew(w: Tensor) -> Tensor:
    """(*bs, 3) -> (*bs, 3, 3) with skew(w) @ v = w × v."""
    z = torch.zeros_like(w[..., 0])
    return torch.stack(
        [z, -w[..., 2], w[..., 1], w[..., 2], z, -w[..., 0], -w[..., 1], w[..., 0], z], -1
    ).reshape(*w.shape[:-1], 3, 3)


def _coeffs(theta: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """sin θ/θ, (1−cos θ)/θ², (θ − sin θ)/θ³ with Taylor forms near θ = 0."""
    small = theta < 1e-3
    t = torch.where(small, torch.ones_like(theta), theta)
    t2 = theta * theta
    a = torch.where(small, 1 - t2 / 6, torch.sin(t) / t)
    b = torch.where(small, 0.5 - t2 / 24, (1 - torch.cos(t)) / (t * t))
    c = torch.where(small, 1.0 / 6 - t2 / 120, (t - torch.sin(t)) / (t * t * t))
    return a, b, c


def exp_so3(w: Tensor) -> Tensor:
    """Rotation vector (*bs, 3) -> rotation matrix (*bs, 3, 3) (Rodrigues, MR eq. 3.51)."""
    theta = torch.linalg.vector_norm(w, dim=-1)
    a, b, _ = _coeffs(theta)
    W = skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(W)
    return eye + a[..., None, None] * W + b[..., None, None] * (W @ W)


def exp_se3(w: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """Screw axis (rotation w, translation part v), each (*bs, 3), scaled by its angle ->
    (R (*bs, 3, 3), p (*bs, 3)) of the rigid transform exp([S]θ) (MR eq. 3.88):
    R = exp_so3(w), p = (I + b·W + c·W²) v with b = (1−cos θ)/θ², c = (θ−sin θ)/θ³."""
    theta = torch.linalg.vector_norm(w, dim=-1)
    a, b, c = _coeffs(theta)
    W = skew(w)
    WW = W @ W
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(W)
    R = eye + a[..., None, None] * W + b[..., None, None] * WW
    G = eye + b[..., None, None] * W + c[..., None, None] * WW
    return R, (G @ v[..., None])[..., 0]


def apply_se3(w: Tensor, v: Tensor, x: Tensor) -> Tensor:
    """Move points x (*bs, 3) by exp_se3(w, v) without forming matrices: cheaper on CPU.

    R x + p with R x = x + a (w×x) + b w×(w×x) and p = v + b (w×v) + c w×(w×v).
    """
    theta = torch.linalg.vector_norm(w, dim=-1, keepdim=True)
    a, b, c = _coeffs(theta)
    wx = torch.cross(w, x, dim=-1)
    wv = torch.cross(w, v, dim=-1)
    rx = x + a * wx + b * torch.cross(w, wx, dim=-1)
    p = v + b * wv + c * torch.cross(w, wv, dim=-1)
    return rx + p
