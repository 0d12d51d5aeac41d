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
    assert rig.radius == pytest.approx(1.0, abs=0.01)
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
def test_paths_look_at_the_head(rig, kind):
    P = C.camera_path(kind, 12, rig)
    assert P.shape == (12, 4, 4)
    np.testing.assert_allclose(P[:, 3], np.tile([0, 0, 0, 1.0], (12, 1)))
    for c2w in P:
        R = c2w[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) == pytest.approx(1.0)
        if kind != "static":
            to_head = rig.center - c2w[:3, 3]
            cos = (-R[:, 2]) @ to_head / np.linalg.norm(to_head)
            assert cos == pytest.approx(1.0, abs=1e-9)
        assert np.linalg.norm(c2w[:3, 3] - rig.center) >= rig.min_distance - 1e-9


def test_path_shapes_and_amplitudes(rig):
    np.testing.assert_array_equal(C.camera_path("static", 3, rig)[1], rig.reference)
    orbit = C.camera_path("orbit", 20, rig, amplitude=20)
    d = np.linalg.norm(orbit[:, :3, 3] - rig.center, axis=1)
    np.testing.assert_allclose(d, d[0])
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
    with pytest.raises(UserError, match="missing.json: camera path file does not exist"):
        C.load_poses(tmp_path / "missing.json")
    assert len(C.resample(np.zeros((3, 4, 4)), 7)) == 7
