"""SE(3) exponential maps for the Nerfies deformation field, batched over leading dims.

Equations from Lynch & Park, *Modern Robotics* (2017): the screw-motion exponential (3.88).
The rotation part is `flamenerf.geometry.so3_exp`; this module adds the translation, in
torch because the warp is trained through it.
"""

from __future__ import annotations

import torch
from torch import Tensor

from flamenerf.geometry import rodrigues_coefficients, skew, so3_exp

def exp_se3(w: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """Screw axis (rotation w, translation part v), each (*bs, 3), scaled by its angle ->
    (R (*bs, 3, 3), p (*bs, 3)) of the rigid transform exp([S]θ) (MR eq. 3.88):
    R = so3_exp(w), p = (I + b·W + c·W²) v with b = (1−cos θ)/θ², c = (θ−sin θ)/θ³."""
    theta = torch.linalg.vector_norm(w, dim=-1)
    _, b, c = rodrigues_coefficients(theta)
    W = skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(W)
    G = eye + b[..., None, None] * W + c[..., None, None] * (W @ W)
    return so3_exp(w), (G @ v[..., None])[..., 0]


def apply_se3(w: Tensor, v: Tensor, x: Tensor) -> Tensor:
    """Move points x (*bs, 3) by exp_se3(w, v) without forming matrices: cheaper on CPU.

    R x + p with R x = x + a (w×x) + b w×(w×x) and p = v + b (w×v) + c w×(w×v).
    """
    theta = torch.linalg.vector_norm(w, dim=-1, keepdim=True)
    a, b, c = rodrigues_coefficients(theta)
    wx = torch.cross(w, x, dim=-1)
    wv = torch.cross(w, v, dim=-1)
    rx = x + a * wx + b * torch.cross(w, wx, dim=-1)
    p = v + b * wv + c * torch.cross(w, wv, dim=-1)
    return rx + p
