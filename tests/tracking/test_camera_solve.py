"""The joint camera solve on synthetic landmarks with known cameras and focal length."""

from __future__ import annotations

import numpy as np
import pytest

from flamenerf.data.dataset import Intrinsics
from flamenerf.geometry import look_at, project_points
from flamenerf.tracking.cameras import SolveConfig, solve_cameras


def synthetic(canonical, n=24, fov=60.0, size=(640, 480), noise=0.3, seed=0):
    rng = np.random.default_rng(seed)
    W, H = size
    f = 0.5 * W / np.tan(np.radians(fov) / 2)
    intr = Intrinsics(W, H, f, f, W / 2, H / 2)
    X = canonical.vertices.copy()
    X[:, 2] += 0.003 * np.sin(12 * X[:, 0])  # this subject differs from the mean face
    t = np.linspace(0, 1, n)
    az = np.radians(-15 + 30 * t)
    d = 0.5
    c2ws = []
    for k in range(n):
        C = d * np.array([np.sin(az[k]), 0.08 + 0.03 * np.sin(6 * t[k]), np.cos(az[k])])
        c2ws.append(look_at(C, np.array([0.0, 0.0, 0.02])))
    c2ws = np.stack(c2ws)
    L = np.zeros((n, 478, 3))
    for k in range(n):
        uv, z = project_points(X, intr, c2ws[k])
        L[k, :468, :2] = uv + rng.normal(0, noise, uv.shape)
        L[k, :468, 2] = (z - z.mean()) * f / z.mean()
    return L, t * 2.0, intr, c2ws, X


def _rot_err_deg(Ra, Rb):
    c = (np.trace(Ra.T @ Rb) - 1) / 2
    return np.degrees(np.arccos(np.clip(c, -1, 1)))


def test_recovers_cameras_with_known_focal(canonical_mesh):
    L, times, intr, c2w_gt, X = synthetic(canonical_mesh)
    cfg = SolveConfig(fov_deg=60.0)
    res = solve_cameras(L, times, canonical_mesh.vertices, canonical_mesh.faces,
                        canonical_mesh.weights, intr.w, intr.h, None, cfg)
    assert res.focal == pytest.approx(intr.fx)
    rot = [_rot_err_deg(a[:3, :3], b[:3, :3]) for a, b in zip(res.c2w, c2w_gt)]
    pos = np.linalg.norm(res.c2w[:, :3, 3] - c2w_gt[:, :3, 3], axis=1)
    assert max(rot) < 1.0
    assert pos.max() < 0.01  # metres, at 0.5 m
    assert np.median(res.rigid_error) < 0.6  # the noise is 0.3 px per axis
    assert np.median(res.mesh_error) < 0.3
    # world-space mesh and cameras agree with the dataset's projection convention
    uv, z = project_points(res.vertices[3].astype(np.float64),
                           Intrinsics(intr.w, intr.h, res.focal, res.focal, res.cx, res.cy),
                           res.c2w[3])
    assert np.all(z > 0)
    assert np.median(np.linalg.norm(uv - L[3, :468, :2], axis=1)) < 0.3


def test_estimates_the_focal_length(canonical_mesh):
    L, times, intr, c2w_gt, X = synthetic(canonical_mesh, noise=0.1)
    res = solve_cameras(L, times, canonical_mesh.vertices, canonical_mesh.faces,
                        canonical_mesh.weights, intr.w, intr.h, None, SolveConfig())
    assert "focal_scan" in res.history
    assert res.focal == pytest.approx(intr.fx, rel=0.2)
    assert np.median(res.rigid_error) < 0.4


@pytest.mark.slow
def test_smoothness_reduces_jitter(canonical_mesh):
    L, times, intr, c2w_gt, _ = synthetic(canonical_mesh, noise=1.5, seed=3)
    kw = dict(template0=canonical_mesh.vertices, faces=canonical_mesh.faces,
              stable_weights=canonical_mesh.weights, width=intr.w, height=intr.h)

    def jitter(smooth):
        res = solve_cameras(L, times, cfg=SolveConfig(fov_deg=60.0, smooth=smooth), **kw)
        C = res.c2w[:, :3, 3]
        return np.linalg.norm(C[2:] - 2 * C[1:-1] + C[:-2], axis=1).mean()

    assert jitter(5.0) < 0.7 * jitter(0.0)


def test_shots_split_at_a_cut_and_not_at_motion():
    from flamenerf.tracking.shots import shot_indices

    y, x = np.mgrid[:32, :32] / 32.0
    # a picture drifting (motion), then another picture
    thumbs = [0.5 + 0.3 * np.sin(6 * (x + 0.02 * k)) * np.cos(4 * y) for k in range(10)]
    thumbs += [0.5 + 0.3 * np.cos(5 * (y + 0.02 * k)) for k in range(6)]
    got = shot_indices(np.stack(thumbs))
    assert got.tolist() == [0] * 10 + [1] * 6
    assert shot_indices(np.stack(thumbs[:10])).tolist() == [0] * 10
    assert shot_indices(np.zeros((1, 32, 32))).tolist() == [0]


@pytest.mark.slow
def test_a_jump_cut_keeps_its_frames(cut_video, canonical_mesh, landmarker_path):
    """An edited clip's jump cut: the solve smoothed the cameras' motion across it, and the
    frames either side of the cut missed their landmarks (three were dropped as misfits);
    now the cut is found and nothing is smoothed across it."""
    from flamenerf.tracking.clip import solve_clip, track_clip

    clip = track_clip(cut_video, progress=False)
    assert clip.cuts == [12]
    assert clip.shots.tolist() == [0] * 12 + [1] * 12
    kept, sol = solve_clip(clip, canonical_mesh, None)
    assert len(kept.frames) == 24 and not kept.dropped
    assert sol.rigid_error.max() < 1.0  # px, at 256 px
