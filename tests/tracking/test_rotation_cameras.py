"""The rotation-only camera model against ground truth: matches of a far background seen by
a turning camera, with outliers, and the model choice against SfM's epipolar geometry."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from flamenerf.tracking.rotation_cameras import (Matches, compare_models, sampson,
                                                 solve_rotations)

F, C, SIZE = 300.0, np.array([160.0, 120.0]), (320, 240)


def _cameras(n: int, rng, deg: float = 3.0) -> np.ndarray:
    """Camera-from-world rotations (n, 3, 3) of a hand's shake: a smooth walk."""
    w = np.cumsum(rng.normal(0, deg / 4, (n, 3)), 0)
    w -= w[0]
    return Rotation.from_rotvec(np.radians(w)).as_matrix()


def _matches(R: np.ndarray, t: np.ndarray, points: np.ndarray, rng, noise: float = 0.3,
             outliers: float = 0.0) -> Matches:
    """Matches of every frame pair up to 4 apart: points (P, 3) world, cameras x = R X + t."""
    n = len(R)
    cam = np.einsum("nab,pb->npa", R, points) + t[:, None]
    px = F * cam[..., :2] / cam[..., 2:] + C + rng.normal(0, noise, cam[..., :2].shape)
    seen = (cam[..., 2] > 0) & (px >= 0).all(-1) & (px[..., 0] < SIZE[0]) & (px[..., 1] < SIZE[1])
    II, JJ, XI, XJ = [], [], [], []
    for i in range(n):
        for j in range(i + 1, min(n, i + 5)):
            k = np.flatnonzero(seen[i] & seen[j])
            xj = px[j, k].copy()
            bad = rng.random(len(k)) < outliers  # something that moves by itself
            xj[bad] += rng.normal(0, 8.0, (bad.sum(), 2))
            II += [np.full(len(k), i)]
            JJ += [np.full(len(k), j)]
            XI += [px[i, k]]
            XJ += [xj]
    return Matches(np.concatenate(II), np.concatenate(JJ), np.concatenate(XI),
                   np.concatenate(XJ))


def _angle_deg(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    return np.degrees(Rotation.from_matrix(np.einsum("nab,ncb->nac", A, B)).magnitude())


def _far_points(rng, p: int = 300, depth: float = 20.0) -> np.ndarray:
    d = np.stack([rng.uniform(-0.6, 0.6, p), rng.uniform(-0.45, 0.45, p), np.ones(p)], 1)
    return d * rng.uniform(0.8, 1.2, (p, 1)) * depth


def test_rotations_of_a_turning_camera_are_recovered_despite_outliers():
    rng = np.random.default_rng(0)
    R = _cameras(24, rng)
    m = _matches(R, np.zeros((24, 3)), _far_points(rng), rng, outliers=0.15)
    sol = solve_rotations(m, 24, F, C)
    assert sol.connected.all()
    assert _angle_deg(sol.R, R).max() < 0.05
    # the outliers stand out, the rest fit to the noise
    assert np.median(sol.residual) < 1.0
    assert (sol.residual > 4).mean() > 0.1


def test_frames_without_matches_to_the_rest_are_not_connected():
    rng = np.random.default_rng(1)
    R = _cameras(10, rng)
    m = _matches(R, np.zeros((10, 3)), _far_points(rng), rng)
    m = m.where((m.i != 9) & (m.j != 9))  # frame 9 matched nothing
    sol = solve_rotations(m, 10, F, C)
    assert sol.connected[:9].all() and not sol.connected[9]


def _sfm_residuals(m: Matches, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return sampson(m, np.concatenate([R, t[..., None]], 2), F, C)


def test_gric_chooses_rotation_for_a_far_background_and_sfm_for_parallax():
    rng = np.random.default_rng(2)
    n = 16
    R = _cameras(n, rng)
    # the camera centre moves 2 cm; background 20 m away (no parallax) or 1-3 m (parallax)
    centres = np.cumsum(rng.normal(0, 0.005, (n, 3)), 0)
    t = -np.einsum("nab,nb->na", R, centres)
    far = _matches(R, t, _far_points(rng), rng)
    near_pts = _far_points(rng, depth=1.0) * rng.uniform(1, 3, (300, 1))
    slide = -np.einsum("nab,nb->na", R, centres * 10)  # 20 cm of travel
    near = _matches(R, slide, near_pts, rng)
    for m, tt, want in ((far, t, "rotation"), (near, slide, "sfm")):
        rot = solve_rotations(m, n, F, C)
        verdict = compare_models(rot.residual, _sfm_residuals(m, R, tt), n)
        assert verdict["chosen"] == want, verdict
