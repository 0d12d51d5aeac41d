import math

import torch

from flamenerf.geometry import skew, so3_exp
from flamenerf.model.se3 import apply_se3, exp_se3


def twist_matrix(w, v):
    T = torch.zeros(4, 4, dtype=torch.float64)
    T[:3, :3] = skew(w)
    T[:3, 3] = v
    return T


def test_identity_at_zero():
    R, p = exp_se3(torch.zeros(3), torch.zeros(3))
    assert torch.allclose(R, torch.eye(3)) and torch.allclose(p, torch.zeros(3))


def test_known_rotation():
    R = so3_exp(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    assert torch.allclose(R @ torch.tensor([1.0, 0, 0], dtype=torch.float64),
                          torch.tensor([0.0, 1, 0], dtype=torch.float64), atol=1e-12)


def test_matches_matrix_exponential_including_small_angles():
    g = torch.Generator().manual_seed(0)
    for scale in [1.0, 1e-2, 1e-5, 0.0]:
        w = torch.randn(3, generator=g, dtype=torch.float64) * scale
        v = torch.randn(3, generator=g, dtype=torch.float64)
        R, p = exp_se3(w, v)
        M = torch.linalg.matrix_exp(twist_matrix(w, v))
        assert torch.allclose(R, M[:3, :3], atol=1e-9), scale
        assert torch.allclose(p, M[:3, 3], atol=1e-9), scale
        x = torch.randn(3, generator=g, dtype=torch.float64)
        assert torch.allclose(apply_se3(w, v, x), R @ x + p, atol=1e-9)


def test_round_trip_inverse():
    w = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)
    v = torch.tensor([0.1, 0.2, -0.3], dtype=torch.float64)
    x = torch.randn(10, 3, dtype=torch.float64)
    y = apply_se3(w.expand(10, 3), v.expand(10, 3), x)
    back = apply_se3(-w.expand(10, 3), -v.expand(10, 3), y)  # exp(-S) = exp(S)^-1
    assert torch.allclose(back, x, atol=1e-9)
    assert torch.allclose(so3_exp(w) @ so3_exp(-w), torch.eye(3, dtype=torch.float64))
