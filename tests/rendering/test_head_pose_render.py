"""Head pose as a control: `render --head-pose` turns the head of a run trained on a scene
with head motion, and leaves the background far from it untouched."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flamenerf.commands.render import render
from flamenerf.data.video import read_frames
from flamenerf.errors import UserError
from flamenerf.rendering.videos import RenderOptions


def _far_from_head(model, intr, c2w, transforms) -> np.ndarray:
    """Pixels none of whose ray samples any of the head transforms moves."""
    from flamenerf.data.rays import camera_rays
    from flamenerf.data.head_pose import transform_points

    o, d = camera_rays(intr, c2w)
    t = torch.linspace(model.near, model.far, 128)
    x = (o[..., None, :] + t[:, None] * d[..., None, :]).reshape(-1, 3).double().numpy()
    w = [model.head_weight(torch.from_numpy(transform_points(T, x)).float()) for T in transforms]
    return (torch.stack(w).amax(0).reshape(intr.h, intr.w, -1).amax(-1) == 0).numpy()


@pytest.mark.slow
def test_head_pose_turns_the_head_not_the_far_background(head_run):
    from flamenerf.data.prior import dataset_dilation
    from flamenerf.geometry import se3_log
    from flamenerf.rendering.reanimate import render_sequence
    from flamenerf.rendering.videos import head_transforms
    from flamenerf.training.run import load_run

    run = load_run(head_run, "cpu")
    ds = run.dataset(None)
    intr = run.train_intrinsics(ds)
    T = head_transforms(RenderOptions(head_run, head_pose=["yaw=25,pitch=-8"]), run, ds, 3)
    assert np.allclose(T[0], np.eye(4)) and not np.allclose(T[1], np.eye(4))
    c2w = ds.frames[0].c2w
    verts = np.repeat(ds.face_vertices[:1], 3, 0)
    omega, phi = run.frame_codes(0)
    args = (run.model, ds, intr, np.repeat(c2w[None], 3, 0), ds.expression_matrix(
        [ds.frames[0]] * 3), verts, omega, phi, dataset_dilation(ds))
    still = list(render_sequence(*args))
    turned = list(render_sequence(*args, heads=se3_log(T).astype(np.float32)))
    assert np.array_equal(still[0].rgb, turned[0].rgb)  # frame 0's pose: identity
    far = _far_from_head(run.model, intr, c2w, [np.eye(4), T[1]])
    diff = np.abs(still[1].rgb - turned[1].rgb).max(-1)
    assert far.mean() > 0.2 and (diff[far] == 0).all()
    assert diff[~far].max() > 1e-3


@pytest.mark.slow
def test_render_cli_head_pose(head_run, toy_run, tmp_path):
    out = tmp_path / "h.mp4"
    render(RenderOptions(head_run, out=out, head_pose=["yaw=20,pitch=-5", "roll=5"], frames=4,
                         device="cpu"))
    assert len(read_frames(out)) == 4
    render(RenderOptions(head_run, out=tmp_path / "n.mp4", split="novel_pose", device="cpu"))
    assert len(read_frames(tmp_path / "n.mp4")) == 2
    with pytest.raises(UserError, match="head poses"):
        render(RenderOptions(toy_run, out=tmp_path / "x.mp4", head_pose=["yaw=10"],
                             device="cpu"))
    with pytest.raises(UserError, match="--head-pose"):
        render(RenderOptions(head_run, out=tmp_path / "y.mp4", head_pose=["tilt=3"],
                             device="cpu"))


@pytest.mark.slow
def test_head_pose_from_a_driving_video(head_run, astronaut_video, tmp_path):
    from flamenerf.rendering.expressions import ExpressionSequence
    from flamenerf.rendering.videos import head_transforms
    from flamenerf.training.run import load_run

    run = load_run(head_run, "cpu")
    ds = run.dataset(None)
    rows = np.array([[0, 0, 0, 0, 0, 0], [25, -8, 3, 0, 0, 0]], np.float32)
    seq = ExpressionSequence(np.zeros((2, ds.expression_dim), np.float32), "d",
                             head_pose=rows)
    T = head_transforms(RenderOptions(head_run, head_pose=["drive"]), run, ds, 2, seq=seq)
    want = head_transforms(RenderOptions(head_run, head_pose=[str(_json(tmp_path, rows))]),
                           run, ds, 2)
    np.testing.assert_allclose(T, want, atol=1e-9)
    with pytest.raises(UserError, match="--drive"):
        head_transforms(RenderOptions(head_run, head_pose=["drive"]), run, ds, 2)
    out = tmp_path / "d.mp4"  # end to end: the driving clip's turns and expressions
    render(RenderOptions(head_run, out=out, drive=astronaut_video, head_pose=["drive"],
                         max_frames=3, device="cpu"))
    assert len(read_frames(out)) == 3


def _json(tmp_path, rows):
    import json

    p = tmp_path / "poses.json"
    p.write_text(json.dumps([dict(zip(("yaw", "pitch", "roll"), map(float, r[:3])))
                             for r in rows]))
    return p


@pytest.mark.slow
def test_train_options_grow_the_head_region(tmp_path):
    """`train --head-region-scale/--head-band` reach the run's config and its model's
    ellipsoid; a non-positive value is a one-line error."""
    from flamenerf.cli import main
    from flamenerf.data.head_pose import head_region
    from flamenerf.synthetic.scene import make_scene
    from flamenerf.training.run import load_run

    ds = make_scene(tmp_path / "scene", seed=3, size=24, frames=4, sway=0.0, reanimate=0,
                    leakage_steps=0, workers=1, head_motion=True)
    out = tmp_path / "run"
    assert main(["train", str(ds), "--out", str(out), "--steps", "1", "--batch-rays", "32",
                 "--head-region-scale", "1.3", "--head-band", "0.5"]) == 0
    run = load_run(out, "cpu")
    assert run.config.model.head.region_scale == 1.3 and run.config.model.head.band == 0.5
    base = head_region(run.dataset(None), 1.0)
    assert np.allclose(run.model.head_rig.radii.cpu().numpy(), 1.3 * base.radii, rtol=1e-5)
    assert main(["train", str(ds), "--out", str(tmp_path / "bad"), "--steps", "1",
                 "--head-band", "0"]) == 2
