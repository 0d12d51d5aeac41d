"""The bake (splats with per-control offsets), its reference rasteriser and `render
--baked` (the exported page in a browser: tests/viewer/test_web_export.py)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from flamenerf.cli import main
from flamenerf.data.dataset import Intrinsics, reference_position
from flamenerf.errors import UserError
from flamenerf.evaluation.metrics import psnr
from flamenerf.model.inference import FAST
from flamenerf.model.render_image import render_image
from flamenerf.splats.avatar import load_avatar, save_avatar
from flamenerf.splats.rasterise import rasterise, render_avatar
from flamenerf.training.run import load_run
from flamenerf.workflows.bake import bake_run, bake_views, snapped_depth

INTR = Intrinsics(24, 20, 30.0, 30.0, 12.0, 10.0)
CAM = np.eye(4)  # at the origin, looking down -z


def _plane(depth: float, colour=(0.2, 0.5, 0.8), size_px: float = 3.0):
    """One splat per pixel of INTR on the plane z = -depth, as the bake places them."""
    ys, xs = np.mgrid[0:INTR.h, 0:INTR.w] + 0.5
    p = np.stack([(xs - INTR.cx) / INTR.fx * depth, -(ys - INTR.cy) / INTR.fy * depth,
                  -depth * np.ones_like(xs)], -1).reshape(-1, 3)
    col = np.random.default_rng(0).random((len(p), 3)) if colour is None else np.tile(
        colour, (len(p), 1))
    return p.astype(np.float32), col.astype(np.float32), np.full(len(p), size_px * depth
                                                                  / INTR.fx, np.float32)


def test_each_splat_keeps_its_own_pixel_from_the_view_it_was_baked_from():
    pos, col, size = _plane(2.0, colour=None)  # three pixels wide: they overlap
    out = rasterise(pos, col, size, CAM, INTR)
    assert out["hit"].all()
    np.testing.assert_allclose(out["rgb"].reshape(-1, 3).numpy(), col, atol=1e-6)
    np.testing.assert_allclose(out["depth"].numpy(), 2.0, rtol=1e-5)


def test_the_nearest_splat_wins_and_nothing_falls_behind_the_camera():
    near = _plane(1.0, (1, 0, 0))
    far = _plane(3.0, (0, 1, 0))
    behind = (np.array([[0, 0, 1.0]], np.float32), np.ones((1, 3), np.float32),
              np.ones(1, np.float32))
    pos, col, size = (np.concatenate(a) for a in zip(far, near, behind))
    out = rasterise(pos, col, size, CAM, INTR)
    assert (out["rgb"].numpy() == [1, 0, 0]).all()
    none = rasterise(*behind, CAM, INTR)
    assert not none["hit"].any() and (none["rgb"].numpy() == 0).all()


def test_a_pixel_on_a_depth_edge_moves_to_the_nearer_side():
    d = torch.full((6, 6), 3.0)
    d[:, :3] = 1.0
    d[2, 3] = 1.4  # a ray grazing the near side
    d[4, 3] = 2.7
    s = snapped_depth(d)
    assert s[2, 3] == 1.0 and s[4, 3] == 3.0 and s[0, 0] == 1.0 and s[0, 5] == 3.0


@pytest.fixture(scope="module")
def baked(toy_run, tmp_path_factory):
    """A copy of the toy run, baked from 3 views into its baked.npz."""
    run_dir = tmp_path_factory.mktemp("bake") / "run"
    shutil.copytree(toy_run, run_dir)
    run = load_run(run_dir, "cpu")
    ds = run.dataset()
    intr = run.train_intrinsics(ds)
    views = bake_views(ds, 3)
    avatar, added = bake_run(run, ds, intr, views, progress=False)
    path = save_avatar(avatar, run_dir / "baked.npz")
    return run, ds, intr, views, load_avatar(path), added


def test_the_bake_draws_its_first_view_as_the_run_renders_it(baked):
    run, ds, intr, views, avatar, added = baked
    assert added[0] == intr.w * intr.h and sum(added) == avatar.n
    ref = ds.frames[reference_position(ds)].expression
    w, a = run.frame_codes(0)
    nerf = render_image(run.model, intr, views[0], w, a, torch.as_tensor(ref),
                        np.ones((intr.h, intr.w), bool), settings=FAST)["rgb"].numpy()
    got = render_avatar(avatar, ref, views[0], intr)["rgb"].numpy()
    assert psnr(got, nerf) > 35  # colours quantised to bytes, later views' splats near it


def test_the_expression_moves_only_the_face_splats(baked):
    run, ds, intr, views, avatar, _ = baked
    assert 0 < len(avatar.face_index) < avatar.n
    moved = avatar.high.copy()
    pos, col = avatar.at(moved)
    rest = np.setdiff1d(np.arange(avatar.n), avatar.face_index)
    assert np.array_equal(pos[rest], avatar.positions[rest])
    assert np.array_equal(col[rest], np.clip(avatar.colours[rest], 0, 1))
    assert not np.allclose(col[avatar.face_index], avatar.colours[avatar.face_index])


def test_a_damaged_bake_is_one_line(tmp_path, baked):
    bad = tmp_path / "baked.npz"
    bad.write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(UserError, match="not a baked avatar"):
        load_avatar(bad)
    np.savez(bad, header=np.array([object()], dtype=object))  # a pickle inside
    with pytest.raises(UserError, match="baked.npz"):
        load_avatar(bad)


def test_render_baked_writes_a_video_and_refuses_a_head_pose(baked, tmp_path, capsys):
    run_dir = baked[0].run_dir
    out = tmp_path / "baked.mp4"
    assert main(["render", str(run_dir), "--baked", "--expressions", "jawOpen=0.8",
                 "--frames", "4", "--out", str(out), "--device", "cpu"]) == 0
    assert out.stat().st_size > 0
    assert main(["render", str(run_dir), "--baked", "--head-pose", "yaw=10",
                 "--out", str(tmp_path / "x.mp4")]) == 2
    assert "--head-pose" in capsys.readouterr().err
