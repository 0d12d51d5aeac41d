"""Rotations, cameras and projection (flamenerf.geometry) against closed forms."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flamenerf import geometry as G


def _skew(v):
    return torch.tensor([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]],
                        dtype=torch.float64)


@pytest.mark.parametrize("scale", [0.0, 1e-5, 0.3, 2.5])
def test_so3_exp_matches_matrix_exp(scale):
    v = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64) * scale
    want = torch.linalg.matrix_exp(_skew(v))
    torch.testing.assert_close(G.so3_exp(v), want, atol=1e-12, rtol=0)


def test_so3_exp_has_a_finite_gradient_at_the_identity():
    w = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    (g,) = torch.autograd.grad(G.so3_exp(w)[0, 1], w)
    torch.testing.assert_close(g, torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64))


def test_numpy_rotations_agree_with_so3_exp():
    w = np.array([0.3, -0.5, 0.8])
    R = G.so3_exp(torch.from_numpy(w)).numpy()
    np.testing.assert_allclose(G.matrix_to_rotvec(R), w, atol=1e-12)
    angle = np.linalg.norm(w)
    # quaternion (w, x, y, z) of a rotation by `angle` about axis k
    k = w / angle
    q = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * k]) * 3.0  # any norm
    np.testing.assert_allclose(G.quat_wxyz_to_matrix(q), R, atol=1e-12)


def test_rotation_between_is_the_smallest_turn():
    a, b = np.array([0.2, 0.1, -0.9]), np.array([-0.5, 0.3, -0.6])
    R = G.rotation_between(a, b)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ (a / np.linalg.norm(a)), b / np.linalg.norm(b), atol=1e-12)
    axis = np.cross(a, b)
    np.testing.assert_allclose(R @ axis, axis, atol=1e-12)  # turns about a x b only
    np.testing.assert_allclose(G.rotation_between(a, 3 * a), np.eye(3), atol=1e-12)


def test_look_at_uses_opengl_axes():
    c2w = G.look_at(np.array([0, 0, 2.0]), np.zeros(3), np.array([0, 1.0, 0]))
    np.testing.assert_allclose(c2w[:3, :3], np.eye(3), atol=1e-12)  # looks down -z
    c2w = G.look_at(np.array([2.0, 0, 0]), np.zeros(3), np.array([0, 1.0, 0]))
    np.testing.assert_allclose(-c2w[:3, 2], [-1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(c2w[:3, 1], [0, 1, 0], atol=1e-12)


def test_look_at_roll_turns_the_camera_about_its_axis():
    eye, target = np.array([0.3, 0.2, 2.0]), np.zeros(3)
    flat, rolled = G.look_at(eye, target), G.look_at(eye, target, roll_deg=90.0)
    np.testing.assert_allclose(rolled[:3, 2], flat[:3, 2], atol=1e-12)
    np.testing.assert_allclose(rolled[:3, 0], flat[:3, 1], atol=1e-12)  # right <- up
    np.testing.assert_allclose(rolled[:3, 1], -flat[:3, 0], atol=1e-12)


def test_projection_of_a_looked_at_point_is_the_principal_point():
    class Intr:
        fx, fy, cx, cy = 500.0, 400.0, 320.0, 240.0

    c2w = G.look_at(np.array([0.4, 0.3, 1.5]), np.array([0.1, 0.0, 0.0]))
    pts = np.array([[0.1, 0.0, 0.0], [0.15, 0.05, 0.02]])
    uv, z = G.project_points(pts, Intr, c2w)
    np.testing.assert_allclose(uv[0], [320.0, 240.0], atol=1e-9)
    assert z[0] == pytest.approx(np.linalg.norm([0.3, 0.3, 1.5]))
    # torch and NumPy give the same pixels
    pc = (pts - c2w[:3, 3]) @ c2w[:3, :3]
    uv_t = G.project(torch.from_numpy(pc), 500.0, 400.0, 320.0, 240.0, min_depth=1e-6)
    np.testing.assert_allclose(uv_t.numpy(), uv, atol=1e-9)


def test_head_euler_inverts_euler_head():
    from flamenerf.geometry import euler_head, head_euler

    for ypr in ([20.0, -5.0, 3.0], [-40.0, 12.0, -7.0], [0.0, 0.0, 0.0]):
        np.testing.assert_allclose(head_euler(euler_head(*ypr)), ypr, atol=1e-9)


def test_relative_head_pose_of_the_landmarker_matrices():
    from flamenerf.geometry import euler_head
    from flamenerf.tracking.driving import relative_head_pose

    R0 = euler_head(5.0, 10.0, -2.0) @ np.diag([1.0, 1.0, 1.0])
    poses = []
    for ypr in ([0, 0, 0], [20, -5, 3], [-15, 8, 0]):
        M = np.eye(4)
        M[:3, :3] = 1.3 * R0 @ euler_head(*ypr)  # the landmarker's matrices carry a scale
        M[:3, 3] = [1.0, 2.0, -40.0]
        poses.append(M)
    rows = relative_head_pose(np.stack(poses))
    np.testing.assert_allclose(rows[:, :3], [[0, 0, 0], [20, -5, 3], [-15, 8, 0]], atol=1e-4)
    assert (rows[:, 3:] == 0).all()


def test_rotation_angle_is_the_relative_rotations_magnitude_and_broadcasts():
    from scipy.spatial.transform import Rotation

    from flamenerf.geometry import rotation_angle_deg

    A = Rotation.from_rotvec([[0.0, 0.3, 0.0], [0.1, 0.0, 0.0]]).as_matrix()
    B = Rotation.from_rotvec([0.0, 0.1, 0.0]).as_matrix()
    np.testing.assert_allclose(rotation_angle_deg(A, B)[0], np.degrees(0.2), rtol=1e-9)
    assert rotation_angle_deg(A, B).shape == (2,)
    assert rotation_angle_deg(B, B) == pytest.approx(0.0, abs=1e-9)
