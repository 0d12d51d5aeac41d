"""Colour at new cameras as the capture saw it: the direction a ray's colour is taken at
stays within a set angle of the nearest captured view (data/captured_views.py)."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from flamenerf.data.captured_views import CapturedViews
from flamenerf.geometry import se3_log

from test_head_pose import REGION, _model, _rigid


def _arc(degrees) -> np.ndarray:
    """Camera centres at distance 1 from the origin, turned about y by `degrees`."""
    a = np.radians(np.asarray(degrees, np.float64))
    return np.stack([np.sin(a), np.zeros_like(a), np.cos(a)], -1).astype(np.float32)


def _angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.rad2deg(torch.acos((F.normalize(a, dim=-1) * F.normalize(b, dim=-1))
                                    .sum(-1).clamp(-1, 1)))


def _aimed(origins: torch.Tensor, rng) -> torch.Tensor:
    """Directions from `origins` towards points near the origin (the focus)."""
    target = torch.from_numpy(rng.normal(0, 0.05, (len(origins), 3))).float()
    return F.normalize(target - origins, dim=-1)


def test_rays_from_captured_cameras_keep_their_direction_others_turn_back():
    m = _model(None).eval()
    m.set_captured_views(CapturedViews(_arc([-10, -5, 0, 5, 10]), None, np.zeros(3, np.float32)),
                         math.radians(2.0))
    rng = np.random.default_rng(0)
    own = torch.from_numpy(_arc([-10, 0, 5, 10])).float()
    d = _aimed(own, rng)
    assert (m.captured_direction(own, d, None, None) - d).abs().max() < 1e-6
    # 1 degree beside the capture: within the limit, as asked
    near = torch.from_numpy(_arc([11.0, -11.0])).float()
    d = _aimed(near, rng)
    assert torch.equal(m.captured_direction(near, d, None, None), d)
    # 30 degrees beyond the last camera: turned to 2 degrees from what the camera at 10
    # degrees saw of the ray's point nearest the focus
    far = torch.from_numpy(_arc([40.0, -40.0])).float()
    d = _aimed(far, rng)
    got = m.captured_direction(far, d, None, None)
    xb = far + ((-far) * d).sum(-1, keepdim=True) * d
    cam = torch.from_numpy(_arc([10.0, -10.0])).float()
    assert torch.allclose(_angle(got, xb - cam), torch.full((2,), 2.0), atol=1e-3)
    assert bool((_angle(got, d) > 25).all())
    # limit 0: exactly the captured view
    m.captured_max_angle = 0.0
    assert _angle(m.captured_direction(far, d, None, None), xb - cam).max() < 1e-2


def test_only_rendering_uses_the_captured_views():
    m = _model(None)
    o = torch.from_numpy(_arc([40.0] * 3)).float()
    d = _aimed(o, np.random.default_rng(1))
    t = torch.linspace(0.6, 1.4, 8).expand(3, -1)
    m.set_captured_views(CapturedViews(_arc([0.0]), None, np.zeros(3, np.float32)), 0.0)
    m.train()
    assert torch.allclose(m.sample_points(o, d, t, None, None)[1], d)  # training: as asked
    m.eval()
    turned = m.sample_points(o, d, t, None, None)[1]
    assert bool((_angle(turned, d) > 30).all())
    m.set_captured_views(None)
    assert torch.allclose(m.sample_points(o, d, t, None, None)[1], d)


def test_with_head_poses_each_training_ray_keeps_its_direction():
    # the capture's centres move with each ray's share of its head twist, so that a ray of
    # a training frame, through the head, its blend band or the still world, keeps its own
    m = _model(REGION).eval()
    rng = np.random.default_rng(5)
    xi = np.stack([se3_log(np.linalg.inv(_rigid(rng))) for _ in range(4)]).astype(np.float32)
    world = _arc([-8, 0, 8, 16])
    m.set_captured_views(CapturedViews(world, xi, np.zeros(3, np.float32)), 0.0)
    rows = np.repeat(np.arange(4), 6)
    o = torch.from_numpy(world[rows]).float()
    target = torch.from_numpy(rng.normal(0, 0.25, (len(o), 3))).float()
    d = F.normalize(target - o, dim=-1)
    head = torch.from_numpy(xi[rows]).float()
    t = torch.linspace(0.3, 1.7, 48).expand(len(o), -1)
    _, dc, share = m._head_points(o[:, None] + t[..., None] * d[:, None], d, head)
    assert bool((share >= 1).any() and (share == 0).any() and ((share > 0) & (share < 1)).any())
    dc = F.normalize(dc, dim=-1)
    assert _angle(m.captured_direction(o, dc, head, share), dc).max() < 0.01
    # the same rays with another frame's twist are not a captured view: they turn
    other = torch.from_numpy(xi[(rows + 2) % 4]).float()
    _, dc2, share2 = m._head_points(o[:, None] + t[..., None] * d[:, None], d, other)
    dc2 = F.normalize(dc2, dim=-1)
    moved = share2 >= 1
    assert bool(moved.any())
    assert _angle(m.captured_direction(o, dc2, other, share2), dc2)[moved].max() > 1.0
