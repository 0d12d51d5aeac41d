"""The handheld variant of the built-in scene: the phone's shake, the far skyline and the
swaying leaves, the person and moving masks, and its dataset."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from flamenerf.data.dataset import load_dataset
from flamenerf.data.dataset_checks import DatasetError
from flamenerf.geometry import head_euler
from flamenerf.synthetic.background import FAR_Z, LEAVES_RECT, LEAVES_Z
from flamenerf.synthetic.cameras import DISTANCE, TARGET, handheld_path, orbit
from flamenerf.synthetic.head import CONTROLS
from flamenerf.synthetic.motion import head_pose
from flamenerf.synthetic.render import SyntheticScene, mask_dilation
from flamenerf.synthetic.scene import handheld_capture, make_scene, scene_from_dataset

SIZE = 48


@pytest.fixture(scope="module")
def handheld():
    # seed 3 as in test_scene.py: the head, the slow part, is built once for both
    return SyntheticScene(seed=3, size=SIZE, sway=0.0, handheld=True)


def _expr(**controls: float) -> np.ndarray:
    e = np.zeros(len(CONTROLS), np.float32)
    for k, v in controls.items():
        e[CONTROLS.index(k)] = v
    return e


def _rotation_deg(R: np.ndarray) -> np.ndarray:
    """Rotation angles (n,) in degrees of rotations (n, 3, 3)."""
    return np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1, 1)))


# ----------------------------------------------------------------------------- the camera


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_handheld_path_shakes_a_few_degrees_and_cm_mostly_rotation(seed):
    c2w = handheld_path(300, seed)
    assert c2w.shape == (300, 4, 4)
    assert np.allclose(c2w[:, :3, :3] @ c2w[:, :3, :3].transpose(0, 2, 1), np.eye(3), atol=1e-9)
    ypr = np.abs(head_euler(c2w[:, :3, :3])).max(0)  # peak yaw, pitch, roll
    assert 1.5 < ypr[0] < 4.5 and 1.5 < ypr[1] < 4.5 and 0.7 < ypr[2] < 3.0
    shift = c2w[:, :3, 3] - (TARGET + [0.0, 0.0, DISTANCE])
    peak = np.abs(shift).max(0)
    assert (peak > 0.005).all() and (peak < 0.035).all()
    # the far skyline sees the rotation, hardly the translation: a shift of s moves it
    # by atan(s / distance) against the rotation's whole angle
    rot = np.sqrt((_rotation_deg(c2w[:, :3, :3]) ** 2).mean())
    far = DISTANCE - FAR_Z
    trans = np.degrees(np.arctan(np.sqrt((np.linalg.norm(shift, axis=1) ** 2).mean()) / far))
    assert rot > 5 * trans
    # and the camera does not simply aim at the head from where it is
    to_head = TARGET - c2w[:, :3, 3]
    aim = np.degrees(np.arccos(np.clip(np.einsum("ni,ni->n", -c2w[:, :3, 2], to_head)
                                       / np.linalg.norm(to_head, axis=1), -1, 1)))
    assert np.sqrt((aim ** 2).mean()) > 1.0
    # smooth: a hand, not a jump cut
    steps = _rotation_deg(c2w[1:, :3, :3] @ c2w[:-1, :3, :3].transpose(0, 2, 1))
    assert steps.max() < 1.0 and np.abs(np.diff(shift, axis=0)).max() < 0.005


def test_handheld_path_is_deterministic_per_seed():
    np.testing.assert_array_equal(handheld_path(50, 4), handheld_path(50, 4))
    assert not np.allclose(handheld_path(50, 4), handheld_path(50, 5))


def test_leaves_sway_several_pixels_per_frame_at_128px(handheld):
    leaves = handheld.backdrop.prims[handheld.backdrop.moving[0]]
    x0, x1, y0, y1 = LEAVES_RECT
    a, b = (g.reshape(-1) for g in torch.meshgrid(torch.linspace(x0, x1, 12),
                                                  torch.linspace(y0, y1, 24), indexing="ij"))
    pixel = (DISTANCE - LEAVES_Z) / (1.55 * 128)  # metres per pixel at 128 px
    du, dv = zip(*(leaves.wind(a, b, t) for t in range(61)))
    du, dv = torch.stack(du), torch.stack(dv)
    assert du[0].abs().max() == 0 and dv[0].abs().max() == 0  # at rest at time 0
    speed = torch.sqrt(du.diff(dim=0) ** 2 + dv.diff(dim=0) ** 2) / pixel
    assert 2.0 < float(speed.median()) < 8.0
    # not a rigid shift: parts of the panel move differently
    assert float((du - du.mean(1, keepdim=True)).abs().max()) / pixel > 2.0


# ----------------------------------------------------------------------------- masks and time


def test_only_the_leaves_change_with_time(handheld):
    c2w, e, hp = orbit(0.0, 0.0), _expr(jawOpen=0.4), head_pose(8, -3, 1)
    a = handheld.render(c2w, e, head_pose=hp, time=0)
    b = handheld.render(c2w, e, head_pose=hp, time=4)
    assert np.array_equal(handheld.render(c2w, e, head_pose=hp).rgb, a.rgb)  # None: time 0
    moving = a.moving
    assert np.array_equal(moving, b.moving) and np.array_equal(a.person, b.person)
    assert 0.05 < moving.mean() < 0.3
    assert not (moving & a.person).any()
    changed = np.abs(a.rgb - b.rgb).max(-1) > 0
    assert changed[moving].mean() > 0.5
    assert not changed[~moving].any()
    # a background pixel far from the leaves: the top-left corner (the skyline)
    far = ~ndimage.binary_dilation(moving, iterations=5) & ~a.person
    assert far[0, 0] and a.depth[0, 0] > 4.0 and not changed[0, 0]
    np.testing.assert_array_equal(a.depth, b.depth)


def test_person_mask_covers_the_face_and_is_the_near_geometry(handheld):
    v = handheld.render(orbit(6.0, 2.0), _expr(), head_pose=head_pose(-15, 5, 2))
    core = ndimage.binary_erosion(v.mask, iterations=mask_dilation(handheld.intr) + 1)
    assert core.sum() > 50 and v.person[core].all()
    assert v.person[v.mask].mean() > 0.9
    # the person is the near geometry (under 1 m); nothing else is that near
    # (a pixel is the person's if any of its rays sees it; its depth is the centre ray's)
    assert (v.depth[v.person] < 1.0).mean() > 0.9 and (v.depth[~v.person] > 1.0).all()


def test_default_scene_ignores_time_and_has_no_moving_pixels():
    scene = SyntheticScene(seed=3, size=SIZE, sway=1.0)
    c2w, e, pose = orbit(-8.0, 3.0), _expr(mouthSmileLeft=0.7), scene.body_pose(7)
    a = scene.render(c2w, e, pose)
    b = scene.render(c2w, e, pose, time=23.0)
    for k in ("rgb", "depth", "mask", "face_vertices", "person", "moving"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    assert not a.moving.any() and 0.1 < a.person.mean() < 0.9
    assert a.person[ndimage.binary_erosion(a.mask, iterations=3)].all()


@pytest.mark.slow
def test_leaves_stay_clear_of_the_person_through_a_capture():
    cover = []
    for f in handheld_capture(seed=0, size=SIZE, frames=60, workers=1):
        assert f.moving.any()
        assert not (ndimage.binary_dilation(f.person, iterations=1) & f.moving).any()
        cover.append(f.moving.mean())
    assert 0.05 < np.mean(cover) < 0.25


# ----------------------------------------------------------------------------- the dataset


@pytest.fixture(scope="module")
def handheld_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("handheld") / "scene"
    # no sway given: handheld makes it 0
    return make_scene(out, seed=3, size=32, frames=4, reanimate=1, leakage_steps=0,
                      workers=1, handheld=True)


def test_handheld_dataset_loads_with_head_poses_and_rerenders(handheld_dataset):
    ds = load_dataset(handheld_dataset)
    assert ds.source["handheld"] and ds.source["head_motion"] and ds.has_head_poses
    cap = sorted(ds.split("train") + ds.split("val"), key=lambda f: f.frame_index)
    np.testing.assert_allclose(np.stack([f.c2w for f in cap]), handheld_path(4, 3), atol=1e-12)
    scene = scene_from_dataset(ds)
    assert scene.handheld
    for f in (cap[0], cap[3], ds.split("novel_pose")[0]):
        v = scene.render(f.c2w, f.expression, head_pose=f.head_pose, time=f.frame_index)
        rgb8 = (np.clip(v.rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
        stored = (ds.load_image(f) * 255 + 0.5).astype(np.uint8)
        assert np.abs(rgb8.astype(int) - stored).max() <= 1
        np.testing.assert_array_equal(v.depth, ds.load_depth(f))
    assert ds.load_moving(ds.split("novel_pose")[0]) is None  # only the capture's are stored
    # the ground-truth capture is the dataset's capture
    frames = list(handheld_capture(seed=3, size=32, frames=4))
    assert [f.index for f in frames] == [0, 1, 2, 3]
    for f, g in zip(cap, frames):
        np.testing.assert_array_equal(g.rgb, (ds.load_image(f) * 255 + 0.5).astype(np.uint8))
        np.testing.assert_array_equal(g.mask, ds.load_mask(f) > 0)
        np.testing.assert_array_equal(g.moving, ds.load_moving(f))
        np.testing.assert_allclose(g.head_pose, f.head_pose, atol=1e-12)
        assert set(g.landmarks) == {"eye_left", "eye_right", "mouth"}
        for px in g.landmarks.values():
            assert g.mask[int(px[1]), int(px[0])] and g.person[int(px[1]), int(px[0])]
        assert g.face_pixels.shape == (len(ds.face_vertices[0]), 2)


def test_handheld_refuses_sway(tmp_path):
    with pytest.raises(DatasetError, match="sway must be 0") as e:
        make_scene(tmp_path / "s", size=24, frames=2, sway=1.0, handheld=True)
    assert "\n" not in str(e.value)
    assert not (tmp_path / "s").exists()


def test_cli_synth_handheld_with_video(tmp_path):
    from flamenerf.cli import main
    from flamenerf.data.video import read_frames

    out, video = tmp_path / "hand", tmp_path / "hand.mp4"
    assert main(["synth", str(out), "--handheld", "--size", "24", "--frames", "3",
                 "--reanimate", "1", "--leakage-steps", "0", "--workers", "1",
                 "--video", str(video)]) == 0
    assert load_dataset(out).source["handheld"]
    frames = read_frames(video)
    assert len(frames) == 3 and frames[0].shape == (24, 24, 3)
    assert main(["synth", str(tmp_path / "x"), "--handheld", "--sway", "1"]) == 2
    assert main(["synth", str(tmp_path / "y"), "--video", str(tmp_path / "y.avi")]) == 2
    assert main(["synth", str(tmp_path / "z"), "--video", str(tmp_path / "z" / "c.mp4")]) == 2
    assert not any((tmp_path / n).exists() for n in ("x", "y", "z"))


def test_a_dataset_with_moving_masks_can_be_written_over(tmp_path):
    out = tmp_path / "phone"
    make_scene(out, seed=3, size=32, frames=2, reanimate=0, leakage_steps=0, handheld=True,
               workers=1)
    assert (out / "moving").is_dir()  # its own folder, which it may replace
    make_scene(out, seed=4, size=32, frames=2, reanimate=0, leakage_steps=0, handheld=True,
               workers=1, overwrite=True)
    assert load_dataset(out).source["seed"] == 4
