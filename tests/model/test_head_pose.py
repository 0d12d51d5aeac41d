"""Following a moving head: the transform's maths, the model's head region, and that a
dataset without head poses (or with a head that never moves) trains exactly as before."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch

from flamenerf.config import preset
from flamenerf.data.head_pose import (HeadPoseKey, HeadRegion, control_transform,
                                      head_pose_items)
from flamenerf.errors import UserError
from flamenerf.geometry import euler_head, se3_log
from flamenerf.model.se3 import apply_se3


def _rigid(rng) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = euler_head(*rng.uniform(-40, 40, 3))
    T[:3, 3] = rng.uniform(-0.1, 0.1, 3)
    return T


def test_head_transform_round_trips_world_head_world():
    rng = np.random.default_rng(0)
    x = torch.from_numpy(rng.normal(0, 0.2, (50, 3)))
    for _ in range(5):
        T = _rigid(rng)
        xi = torch.from_numpy(se3_log(T))
        y = apply_se3(xi[None, :3], xi[None, 3:], x)  # world -> head (canonical)
        assert torch.allclose(y, x @ torch.from_numpy(T[:3, :3]).T + torch.from_numpy(T[:3, 3]),
                              atol=1e-10)
        back = apply_se3(-xi[None, :3], -xi[None, 3:], y)  # head -> world
        assert torch.allclose(back, x, atol=1e-10)
    assert np.allclose(se3_log(np.eye(4)), 0)


def test_control_transform_turns_the_head_about_its_centre():
    region = HeadRegion(np.array([0.0, 0.01, -0.02]), np.eye(3), np.array([0.09, 0.12, 0.12]))
    assert np.allclose(control_transform(HeadPoseKey(), region), np.eye(4))
    T = control_transform(HeadPoseKey(yaw=30), region)
    M = np.linalg.inv(T)  # the head's motion in the world
    assert np.allclose(M[:3, :3] @ region.centre + M[:3, 3], region.centre)  # centre stays
    nose = region.centre + [0, 0, 0.1]
    assert (M[:3, :3] @ nose + M[:3, 3])[0] > 0.04  # yaw > 0 turns the face towards +x
    rows, keyframes = head_pose_items(["yaw=20,pitch=-5", "roll=3"])
    assert keyframes and np.allclose(rows, [[20, -5, 0, 0, 0, 0], [0, 0, 3, 0, 0, 0]])
    for bad in ("yaw", "yaw=x", "tilt=3", "yaw=1e9", "x=2"):
        with pytest.raises(UserError, match="--head-pose"):
            head_pose_items([bad])


def _model(region: dict | None):
    from test_model import tiny

    m = tiny("fast", "hash")
    torch.manual_seed(0)
    if region is None:
        return m
    from flamenerf.model.flame_nerf import FlameNeRF

    m2 = FlameNeRF(m.cfg, num_codes=3, expr_dim=5, near=0.5, far=1.5, box_min=[-1] * 3,
                   box_max=[1] * 3, head_region=region)
    m2.load_state_dict(m.state_dict())
    return m2


REGION = {"centre": [0.0, 0.0, 0.0], "axes": np.eye(3).tolist(), "radii": [0.2, 0.25, 0.2]}


def test_head_points_move_the_head_and_leave_the_background():
    m = _model(REGION)
    xi = torch.from_numpy(se3_log(np.linalg.inv(_rigid(np.random.default_rng(3))))).float()
    x = torch.tensor([[[0.0, 0.02, 0.05], [0.9, 0.0, -0.8], [0.0, 0.0, 0.0]]])  # head, far, centre
    d = torch.tensor([[0.0, 0.0, -1.0]])
    xc, dc = m.head_points(x, d, xi[None])
    full = apply_se3(xi[None, :3], xi[None, 3:], x[0])
    assert torch.allclose(xc[0, 0], full[0], atol=1e-6)  # inside: the full rigid motion
    assert torch.equal(xc[0, 1], x[0, 1])  # far away: untouched
    assert torch.allclose(dc[0].norm(), torch.tensor(1.0))
    # no twists, or a model without a head region: exactly the input
    assert m.head_points(x, d, None)[0] is x
    assert _model(None).head_points(x, d, xi[None])[0] is x


def test_head_points_match_the_per_point_screw_everywhere():
    # the head and the still world take a shortcut (one matrix per ray, or nothing); the
    # blend band the per-point screw exp(w ξ): together they equal the screw at every point
    m = _model(REGION)
    rng = np.random.default_rng(4)
    xi = torch.from_numpy(np.stack([se3_log(np.linalg.inv(_rigid(rng))) for _ in range(6)])
                          ).float()
    x = torch.from_numpy(rng.normal(0, 0.2, (6, 40, 3))).float()
    d = torch.nn.functional.normalize(torch.randn(6, 3), dim=-1)
    xc, dc = m.head_points(x, d, xi)
    w = m.head_weight(apply_se3(xi[:, None, :3], xi[:, None, 3:], x))[..., None]
    assert bool((w >= 1).any() and (w == 0).any() and ((w > 0) & (w < 1)).any())
    ref = apply_se3(w * xi[:, None, :3], w * xi[:, None, 3:], x)
    assert (xc - ref).abs().max() < 1e-5
    ref_d = apply_se3(w.amax(1) * xi[:, :3], torch.zeros_like(d), d)
    assert (dc - ref_d).abs().max() < 1e-6


@pytest.mark.slow
def test_the_deformation_stays_in_the_head_region():
    # with head poses the background is static in the world: the warp leaves every point
    # outside the head's region where it is, moves those inside by the full warp and
    # blends in the band; the baked warp of the inference path does the same
    import copy

    from flamenerf.model.baked import baked_warp
    from flamenerf.model.flame_nerf import FlameNeRF

    m = _model(REGION)
    assert not m.warp_in_head  # head_only unset: as trained before the option
    cfg = copy.deepcopy(m.cfg)
    cfg.warp.head_only = True
    h = FlameNeRF(cfg, num_codes=3, expr_dim=5, near=0.5, far=1.5, box_min=[-1] * 3,
                  box_max=[1] * 3, head_region=REGION)
    h.load_state_dict(m.state_dict())
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():  # a warp that moves points visibly (it starts as the identity)
        for p in h.warp.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=g))
    code = h.deform_codes.weight[:2].detach()
    x = torch.rand(2, 400, 3, generator=g) * 1.2 - 0.6
    with torch.no_grad():
        out, full = h.warp_points(x, code[:, None]), h.warp(x, code[:, None])
    w = h.head_weight(x)  # the box is [-1, 1]^3: normalised = world
    still, head, band = w == 0, w >= 1, (w > 0) & (w < 1)
    assert bool(still.any() and head.any() and band.any())
    assert (full[still] - x[still]).abs().max() > 1e-2  # the warp would move them
    assert torch.equal(out[still], x[still])
    assert torch.allclose(out[head], full[head], atol=1e-6)
    blend = x + w[..., None] * (full - x)
    assert torch.allclose(out[band], blend[band], atol=1e-6)
    with torch.no_grad():
        baked = baked_warp(h, code[0], 65)(x[0])
    assert (baked - out[0]).abs().max() < 0.2 * (full[0] - x[0]).abs().max()
    far = h.head_weight(0.8 * x[0]) == 0  # still, and over a voxel from the band
    assert bool(far.any()) and torch.equal(baked[far], x[0][far])
    # the deformation's own, narrower band: points the head's band still blends stay put
    h.cfg.warp.band = 0.1
    with torch.no_grad():
        narrow = h.warp_points(x, code[:, None])
    outside = (h.head_weight(x, 0.1) == 0) & (w > 0)
    assert bool(outside.any()) and torch.equal(narrow[outside], x[outside])
    assert torch.allclose(narrow[head], full[head], atol=1e-6)


def test_zero_head_twists_render_exactly_as_no_head_poses():
    from test_model import rays

    m = _model(REGION).eval()
    r = rays(m, n=16)
    plain = m(r)
    r.head = torch.zeros(16, 6)
    posed = m(r)
    for k in ("rgb", "depth", "acc"):
        assert torch.equal(plain[k], posed[k]), k


def _train_without_and_with_still_head_poses(toy_dataset, tmp_path, everywhere: bool):
    """Two toy trainings of the same capture: as it is (no head poses), and with an identity
    head_pose on every frame. `everywhere`: the deformation acts everywhere in both (else
    it is confined to the head's region, `fast`'s default). -> (runs, datasets)."""
    from toy import toy_config

    from flamenerf.training.run import load_run
    from flamenerf.training.trainer import train

    posed = tmp_path / "posed"
    shutil.copytree(toy_dataset, posed)
    meta = json.loads((posed / "transforms.json").read_text())
    for fr in meta["frames"]:
        fr["head_pose"] = np.eye(4).tolist()
    (posed / "transforms.json").write_text(json.dumps(meta))
    runs = []
    for name, data in (("plain", toy_dataset), ("posed", posed)):
        cfg = toy_config("masked", 3)
        assert cfg.model.warp.still_head_only  # `fast`'s default
        if everywhere:
            cfg.model.warp.head_only = cfg.model.warp.still_head_only = False
        train(data, tmp_path / f"{name}_run", cfg, device="cpu", quiet=True)
        runs.append(load_run(tmp_path / f"{name}_run", "cpu"))
    assert not runs[0].model.follows_head and runs[1].model.follows_head
    return runs, (toy_dataset, posed)


@pytest.mark.slow
def test_confined_warp_trains_alike_with_and_without_still_head_poses(toy_dataset, tmp_path):
    """`fast`'s defaults confine the deformation to the head's region both where the head
    is followed (`warp.head_only`) and where it is not (`warp.still_head_only`): the same
    capture with and without identity head poses trains to the same weights."""
    (a, b), _ = _train_without_and_with_still_head_poses(toy_dataset, tmp_path, False)
    assert a.model.warp_in_head and b.model.warp_in_head
    for (k, va), vb in zip(a.model.state_dict().items(), b.model.state_dict().values()):
        assert torch.allclose(va, vb, atol=1e-6), k


def test_an_unfollowed_moving_head_keeps_the_warp_everywhere(toy_dataset, tmp_path):
    """`fast` with `model.head.follow` off on a dataset with head poses (the `static`
    ablation): the head moves through the world, so its warp is not confined to the
    region around frame 0's head."""
    from toy import toy_config

    from flamenerf.data.dataset import load_dataset
    from flamenerf.data.scene import model_head_region, model_warp_region
    from flamenerf.training.trainer import build_for_dataset

    posed = tmp_path / "posed"
    shutil.copytree(toy_dataset, posed)
    meta = json.loads((posed / "transforms.json").read_text())
    for i, fr in enumerate(meta["frames"]):
        pose = np.eye(4)
        pose[0, 3] = 0.01 * i  # the head slides sideways
        fr["head_pose"] = pose.tolist()
    (posed / "transforms.json").write_text(json.dumps(meta))
    ds = load_dataset(posed)
    cfg = toy_config("masked", 3)
    assert cfg.model.warp.still_head_only
    cfg.model.head.follow = False
    assert model_head_region(cfg, ds) is None and model_warp_region(cfg, ds) is None
    m = build_for_dataset(cfg, ds)
    assert not m.follows_head and not m.warp_in_head


@pytest.mark.slow
def test_still_head_poses_train_exactly_as_no_head_poses(toy_dataset, tmp_path):
    """The same capture with an identity head_pose on every frame: same weights after
    training, same renders (a dataset without head poses behaves as it always did), when
    the deformation acts everywhere as without head poses (`warp.head_only` False; with
    it the still world has no deformation, the test above)."""
    (a, b), datasets = _train_without_and_with_still_head_poses(toy_dataset, tmp_path, True)
    for (k, va), vb in zip(a.model.state_dict().items(), b.model.state_dict().values()):
        assert torch.equal(va, vb), k
    from flamenerf.data.dataset import load_dataset
    from flamenerf.data.scene import FrameSet
    from flamenerf.evaluation.protocol import render_frames

    imgs = []
    for run, data in zip((a, b), datasets):
        ds = load_dataset(data)
        fs = FrameSet(ds, ds.split("val"), run.train_intrinsics(ds))
        om, ph = run.model.codes(fs.frame_index)
        imgs.append(render_frames(run.model, fs, om.detach(), ph.detach()))
    assert all(np.array_equal(x, y) for x, y in zip(*imgs))


@pytest.mark.slow
def test_a_still_head_deforms_only_in_its_region(toy_dataset, tmp_path):
    """`warp.still_head_only`: without head poses the deformation acts in the head's region
    alone (the room's samples skip it), the model does not follow a head, and a loaded run
    rebuilds the region; off, a still head deforms everywhere as before."""
    from toy import toy_config

    from flamenerf.data.dataset import load_dataset
    from flamenerf.data.scene import model_warp_region
    from flamenerf.model.flame_nerf import FlameNeRF
    from flamenerf.training.run import load_run
    from flamenerf.training.trainer import train

    m = _model(None)
    assert not m.warp_in_head
    h = FlameNeRF(m.cfg, num_codes=3, expr_dim=5, near=0.5, far=1.5, box_min=[-1] * 3,
                  box_max=[1] * 3, warp_region=REGION)
    h.load_state_dict(m.state_dict())
    assert h.warp_in_head and not h.follows_head
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for p in h.warp.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=g))
        code = h.deform_codes.weight[:1].detach()
        x = torch.rand(1, 300, 3, generator=g) * 1.2 - 0.6
        out, full = h.warp_points(x, code[:, None]), h.warp(x, code[:, None])
    w = h.head_weight(x, h.cfg.warp.band)
    assert bool((w == 0).any() and (w >= 1).any())
    assert (full[w == 0] - x[w == 0]).abs().max() > 1e-2
    assert torch.equal(out[w == 0], x[w == 0])
    assert torch.allclose(out[w >= 1], full[w >= 1], atol=1e-6)

    ds = load_dataset(toy_dataset)
    paper = preset("flame-in-nerf")
    paper.model.warp.settle()
    assert model_warp_region(paper, ds) is None  # the paper's warp acts everywhere
    cfg = toy_config("masked", 3)  # `fast`'s: in the head's region
    cfg.model.warp.settle()
    assert model_warp_region(cfg, ds) is not None
    train(toy_dataset, tmp_path / "still", cfg, device="cpu", quiet=True)
    run = load_run(tmp_path / "still", "cpu")
    assert run.model.warp_in_head and not run.model.follows_head
    assert run.model.init_args["warp_region"] == model_warp_region(cfg, ds)
