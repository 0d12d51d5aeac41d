"""Camera paths: conventions, shapes, and the constraints the module doc promises."""

from __future__ import annotations

import json

import numpy as np
import pytest

from flamenerf.data.dataset import load_dataset
from flamenerf.errors import UserError
from flamenerf.rendering import cameras as C


@pytest.fixture(scope="module")
def rig(toy_dataset):
    return C.rig_from_dataset(load_dataset(toy_dataset))


def test_rig_from_the_capture(rig):
    np.testing.assert_allclose(rig.center, 0, atol=1e-6)  # the toy face's centroid
    assert rig.swing_deg > 0
    lo, hi = rig.azimuth_range
    assert lo <= 0 <= hi and hi - lo == pytest.approx(2 * rig.swing_deg)
    assert 0.5 < rig.min_distance < 1.0


def test_default_orbit_stays_within_the_captured_azimuths(rig):
    def azimuths(P, r):
        e0 = r.reference[:3, 3] - r.center
        e0 -= r.up * (e0 @ r.up)
        e0 /= np.linalg.norm(e0)
        v = P[:, :3, 3] - r.center
        return np.degrees(np.arctan2(v @ np.cross(r.up, e0), v @ e0))

    from dataclasses import replace

    for lo, hi in ((-2.0, 12.0), (0.0, 0.0), (-7.0, 0.0)):  # frame 0 off-centre, still
        r = replace(rig, azimuth_range=(lo, hi))
        az = azimuths(C.camera_path("orbit", 40, r), r)
        assert az.min() == pytest.approx(lo, abs=0.2) and az.max() == pytest.approx(hi, abs=0.2)
    wide = azimuths(C.camera_path("orbit", 40, r, amplitude=20.0), r)  # asked for: beyond
    assert wide.max() == pytest.approx(20.0, abs=0.2)


@pytest.mark.parametrize("kind", C.PATH_KINDS)
@pytest.mark.parametrize("off_centre", [False, True])
def test_paths_keep_the_head_where_the_reference_sees_it(rig, kind, off_centre):
    from dataclasses import replace

    from flamenerf.geometry import look_at

    if off_centre:  # a crop that put the face left of the image's centre
        ref = look_at(rig.eye, rig.center + np.array([0.15, -0.05, 0.0]), rig.up)
        rig = replace(rig, reference=ref)

    def towards_head(c2w):  # the head's direction in camera axes: its pixel
        v = c2w[:3, :3].T @ (rig.center - c2w[:3, 3])
        return v / np.linalg.norm(v)

    P = C.camera_path(kind, 12, rig)
    assert P.shape == (12, 4, 4)
    np.testing.assert_allclose(P[:, 3], np.tile([0, 0, 0, 1.0], (12, 1)))
    np.testing.assert_allclose(P[0], rig.reference, atol=1e-12)
    for c2w in P:
        R = c2w[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(towards_head(c2w), towards_head(rig.reference), atol=1e-9)
        assert np.linalg.norm(c2w[:3, 3] - rig.center) >= rig.min_distance - 1e-9
    if kind != "static":
        assert np.ptp(P[:, :3, 3], axis=0).max() > 1e-3  # it moves


def test_orbit_keeps_to_the_captures_distance_and_height(rig):
    """A handheld capture's cameras drift in and up as they go round; the orbit follows
    them instead of an arc at frame 0's distance."""
    from dataclasses import replace

    az = np.linspace(-20.0, 20.0, 41)
    v = rig.eye - rig.center
    h0 = v @ rig.up
    r0 = np.linalg.norm(v - h0 * rig.up)
    captured = np.stack([az, r0 - 0.004 * az, h0 + 0.002 * az], 1)
    r = replace(rig, azimuth_range=(-20.0, 20.0), captured=captured)
    for a in (-12.0, 6.0, 15.0):
        e = r.orbit_eye(a) - r.center
        h = e @ r.up
        assert h == pytest.approx(h0 + 0.002 * a, abs=2e-3)
        assert np.linalg.norm(e - h * r.up) == pytest.approx(r0 - 0.004 * a, abs=4e-3)
    np.testing.assert_allclose(r.orbit_eye(0.0), r.eye, atol=1e-12)
    flat = replace(r, captured=None)  # an arc
    d = [np.linalg.norm(flat.orbit_eye(a) - r.center) for a in (-12.0, 15.0)]
    np.testing.assert_allclose(d, np.linalg.norm(v))


def test_default_range_is_where_the_head_was_seen_from_too(tmp_path):
    """Cameras that swing 0..20 deg round a head that turns after them by half as much
    saw the face from 0..10 deg only: the default orbit stays there."""
    from toy import TOY_NAMES

    from flamenerf.data.dataset import Intrinsics
    from flamenerf.data.dataset_writer import DatasetWriter
    from flamenerf.geometry import euler_head, look_at

    intr = Intrinsics(16, 16, 20.0, 20.0, 8.0, 8.0)
    s = 0.1
    verts = np.array([[-s, -s, 0], [s, -s, 0], [s, s, 0], [-s, s, 0]], np.float64)
    up = np.array([0.0, 1.0, 0.0])
    with DatasetWriter(tmp_path / "d", intr, 0.5, 1.6, TOY_NAMES, "synthetic",
                       source={"name": "test"}, prior_dilation_px=1) as w:
        for i, yaw in enumerate(np.linspace(0.0, 20.0, 5)):
            y = np.radians(yaw)
            c2w = look_at(np.array([np.sin(y), 0.0, np.cos(y)]), np.zeros(3), up)
            head = np.eye(4)
            head[:3, :3] = euler_head(yaw / 2, 0.0, 0.0)
            posed = verts @ head[:3, :3].T
            w.add_frame(np.zeros((16, 16, 3), np.float32), np.ones((16, 16), bool), c2w,
                        np.zeros(len(TOY_NAMES)), i, "train", verts=posed.astype(np.float32),
                        head_pose=head)
        w.set_faces(np.array([[0, 1, 2], [0, 2, 3]], np.int32))
    rig = C.rig_from_dataset(load_dataset(tmp_path / "d"))
    lo, hi = rig.azimuth_range
    assert lo == pytest.approx(0.0, abs=1e-6)
    assert abs(hi) == pytest.approx(10.0, abs=0.1)


def test_path_shapes_and_amplitudes(rig):
    np.testing.assert_array_equal(C.camera_path("static", 3, rig)[1], rig.reference)
    orbit = C.camera_path("orbit", 20, rig, amplitude=20)
    d = np.linalg.norm(orbit[:, :3, 3] - rig.center, axis=1)
    np.testing.assert_allclose(d, d[0], rtol=1e-5)  # the toy capture keeps its distance
    np.testing.assert_allclose(orbit[0, :3, 3], rig.eye, atol=1e-12)
    v0, v5 = orbit[0, :3, 3] - rig.center, orbit[5, :3, 3] - rig.center  # a quarter period
    ang = np.degrees(np.arccos(v0 @ v5 / (np.linalg.norm(v0) * np.linalg.norm(v5))))
    assert ang == pytest.approx(20, abs=0.5)
    dolly = C.camera_path("dolly", 20, rig, amplitude=0.2)
    dd = np.linalg.norm(dolly[:, :3, 3] - rig.center, axis=1)
    assert dd.max() <= np.linalg.norm(rig.eye - rig.center) + 1e-9
    assert dd.min() < dd.max()
    with pytest.raises(UserError, match="unknown camera path 'circle'"):
        C.camera_path("circle", 3, rig)


def test_load_poses_formats_and_errors(tmp_path):
    eye = np.eye(4)
    (tmp_path / "a.json").write_text(json.dumps([eye.tolist(), eye.tolist()]))
    (tmp_path / "b.json").write_text(json.dumps({"frames": [{"transform_matrix": eye.tolist()}]}))
    (tmp_path / "c.json").write_text(json.dumps({"poses": [eye[:3].tolist()]}))
    assert C.load_poses(tmp_path / "a.json").shape == (2, 4, 4)
    assert C.load_poses(tmp_path / "b.json").shape == (1, 4, 4)
    np.testing.assert_array_equal(C.load_poses(tmp_path / "c.json")[0], eye)
    (tmp_path / "bad.json").write_text(json.dumps([[1, 2, 3]]))
    with pytest.raises(UserError, match="bad.json: poses must be"):
        C.load_poses(tmp_path / "bad.json")
    away = eye.copy()
    away[2, 3] = 1e30  # finite, rigid, and nowhere near the scene
    (tmp_path / "far.json").write_text(json.dumps([eye.tolist(), away.tolist()]))
    with pytest.raises(UserError, match="far.json: pose 1 is more than 10000 m"):
        C.load_poses(tmp_path / "far.json")
    with pytest.raises(UserError, match="missing.json: camera path file does not exist"):
        C.load_poses(tmp_path / "missing.json")
    assert len(C.resample(np.zeros((3, 4, 4)), 7)) == 7


def test_default_spiral_stays_where_the_capture_filmed(rig):
    """The toy's cameras lie on one arc: the default spiral shrinks to stay near it (a model
    is sure of the scene only near its cameras), an explicit amplitude does not."""
    eyes = rig.captured_eyes()

    def off(P):
        return np.linalg.norm(P[:, None, :3, 3] - eyes[None], axis=-1).min(1).max()

    P = C.camera_path("spiral", 24, rig)
    assert off(P) <= rig.capture_tolerance() + 1e-9
    assert np.ptp(P[:, :3, 3], axis=0).max() > 0.5 * rig.capture_tolerance()  # still moves
    assert off(C.camera_path("spiral", 24, rig, amplitude=20.0)) > rig.capture_tolerance()


def test_a_capture_that_sweeps_an_area_covers_it(rig):
    from dataclasses import replace

    e0, e1 = rig.basis()
    v = rig.eye - rig.center
    h0 = v @ rig.up
    r0 = np.linalg.norm(v - h0 * rig.up)
    t = np.linspace(0, 1, 60)  # a zigzag over +-15 deg and +-0.1 m of height
    zig = np.stack([30 * t - 15, r0 + 0 * t, h0 + 0.1 * np.sign(np.sin(6 * np.pi * t))], 1)
    r = replace(rig, captured=zig)
    between = r.orbit_eye(5.0)  # between the zigzag's passes, far from any of its cameras
    assert np.linalg.norm(r.captured_eyes() - between, axis=1).min() > r.capture_tolerance()
    assert r.near_capture(between[None])[0]
    outside = between + 0.3 * rig.up  # above all of it
    assert not r.near_capture(outside[None])[0]
    line = replace(rig, captured=np.stack([30 * t - 15, r0 + 0 * t, h0 + 0 * t], 1))
    assert not line.near_capture((between + 0.05 * rig.up)[None])[0]
