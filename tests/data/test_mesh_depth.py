import numpy as np
import torch

from flamenerf.data.dataset import Intrinsics
from flamenerf.data.mesh_depth import mesh_depth
from flamenerf.data.rays import pixel_directions
from flamenerf.geometry import look_at
from flamenerf.model.losses import face_depth_loss

INTR = Intrinsics(32, 32, 40.0, 40.0, 16.0, 16.0)


def quad(z: float, s: float) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[-s, -s, z], [s, -s, z], [s, s, z], [-s, s, z]])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def test_mesh_depth_is_the_z_depth_of_the_nearest_triangle():
    c2w = look_at(np.array([0.0, 0.0, 1.0]), np.zeros(3))
    dirs = pixel_directions(INTR).numpy()
    far_v, far_f = quad(0.0, 0.3)  # 1 m from the camera, covers the middle of the image
    near_v, near_f = quad(0.4, 0.05)  # 0.6 m, a smaller square in front of it
    verts = np.concatenate([far_v, near_v])
    faces = np.concatenate([far_f, near_f + 4])
    d = mesh_depth(verts, faces, INTR, c2w, dirs)
    assert np.isclose(d[16, 16], 0.6, atol=1e-5)  # the near square wins where both are
    assert np.isclose(d[16, 5], 1.0, atol=1e-5)  # the far one around it
    assert np.isinf(d[0, 0]) and np.isinf(d[31, 31])  # no mesh at the corners
    # a tilted camera: still z-depth (the ray parameter of data/rays.py), not distance
    c2w = look_at(np.array([0.3, 0.0, 1.0]), np.zeros(3))
    d = mesh_depth(far_v, far_f, INTR, c2w, dirs)
    x = np.array([0.0, 0.0, 0.0, 1.0])
    z = -(np.linalg.inv(c2w) @ x)[2]
    assert np.isclose(d[16, 16], z, atol=2e-2)


def test_face_depth_loss_wants_the_weight_on_the_surface():
    t = torch.linspace(0.5, 1.5, 11)[None].expand(3, -1)
    depth = torch.tensor([1.0, 1.0, float("inf")])
    surface = torch.zeros(3, 11)
    surface[:, 5] = 1.0  # all the weight at t = 1.0
    fog = torch.full((3, 11), 1 / 11)
    assert face_depth_loss(surface, t, depth, 0.01).item() == 0.0
    assert face_depth_loss(fog, t, depth, 0.01).item() > 0.2
    # the ray without a mesh depth does not count; no such ray at all: zero
    assert torch.isclose(face_depth_loss(fog, t, depth, 0.01),
                         face_depth_loss(fog[:2], t[:2], depth[:2], 0.01))
    assert face_depth_loss(fog, t, torch.full((3,), float("inf")), 0.01).item() == 0.0
    # the margin leaves weight close to the surface free
    near = torch.zeros(3, 11)
    near[:, 4] = 1.0  # 0.1 from the surface
    assert face_depth_loss(near, t, depth, 0.15).item() == 0.0
    assert face_depth_loss(near, t, depth, 0.05).item() > 0.04
