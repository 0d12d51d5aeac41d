"""Rotations, cameras and projection: the one home of the project's geometry.

Conventions (the dataset's): camera-to-world 4x4 matrices with OpenGL camera axes (x right,
y up, the camera looks down -z); pixels x right, y down; depth is -z in camera space.

Rotations in NumPy are SciPy's (`scipy.spatial.transform.Rotation`). The SO(3) exponential
is also written here in torch, batched and differentiable, because the camera solve, the
FLAME fit and the deformation field's SE(3) warp (`flamenerf.model.se3`) optimise through
it. Equations from Lynch & Park, *Modern Robotics* (2017): Rodrigues' formula (3.51).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, TypeVar

import numpy as np

if TYPE_CHECKING:  # torch is imported where it is used: `flamenerf --help` stays fast
    from torch import Tensor

Array = TypeVar("Array", np.ndarray, "Tensor")


class Pinhole(Protocol):
    """A pinhole camera's intrinsics in pixels (e.g. `flamenerf.data.dataset.Intrinsics`)."""

    fx: float
    fy: float
    cx: float
    cy: float


# ----------------------------------------------------------------------------- SO(3), torch


def skew(w: Array) -> Array:
    """(*bs, 3) -> (*bs, 3, 3) with skew(w) @ v = w × v (NumPy or torch)."""
    if isinstance(w, np.ndarray):
        xp = np
    else:
        import torch as xp
    z = xp.zeros_like(w[..., 0])
    return xp.stack(
        [z, -w[..., 2], w[..., 1], w[..., 2], z, -w[..., 0], -w[..., 1], w[..., 0], z], -1
    ).reshape(*w.shape[:-1], 3, 3)


def rodrigues_coefficients(theta: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """sin θ/θ, (1−cos θ)/θ², (θ − sin θ)/θ³ of angles θ (*bs), with Taylor forms near
    θ = 0 so that values and gradients stay finite at the identity."""
    import torch

    small = theta < 1e-3
    t = torch.where(small, torch.ones_like(theta), theta)
    t2 = theta * theta
    a = torch.where(small, 1 - t2 / 6, torch.sin(t) / t)
    b = torch.where(small, 0.5 - t2 / 24, (1 - torch.cos(t)) / (t * t))
    c = torch.where(small, 1.0 / 6 - t2 / 120, (t - torch.sin(t)) / (t * t * t))
    return a, b, c


def so3_exp(w: Tensor) -> Tensor:
    """Rotation vector (*bs, 3) -> rotation matrix (*bs, 3, 3) (Rodrigues, MR eq. 3.51)."""
    import torch

    theta = torch.linalg.vector_norm(w, dim=-1)
    a, b, _ = rodrigues_coefficients(theta)
    W = skew(w)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(W)
    return eye + a[..., None, None] * W + b[..., None, None] * (W @ W)


# ----------------------------------------------------------------------------- SO(3), NumPy


def cayley(r: np.ndarray) -> np.ndarray:
    """Rotation of Cayley parameters r (..., 3): exact, smooth at 0 (an optimiser's
    parametrisation near a prior rotation), angle 2·atan|r|. -> (..., 3, 3)"""
    S = skew(r)
    k = 2.0 / (1.0 + (r * r).sum(-1))[..., None, None]
    return np.eye(3) + k * (S + S @ S)


def cayley_grad(r: np.ndarray) -> np.ndarray:
    """dR/dr of `cayley`: (..., 3) -> (..., 3, 3, 3), last axis the parameter."""
    S = skew(r)
    SS = S @ S
    k = 2.0 / (1.0 + (r * r).sum(-1))[..., None, None]
    out = np.zeros(r.shape[:-1] + (3, 3, 3))
    for a, E in enumerate(skew(np.eye(3))):  # E = dS/dr_a
        dk = -k * k * r[..., a][..., None, None]  # d(2/(1+|r|²))/dr_a
        out[..., a] = dk * (S + SS) + k * (E + E @ S + S @ E)
    return out


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (*bs, 3, 3) -> rotation vectors (*bs, 3)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


def rotation_angle_deg(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """The angle (degrees) of the rotation between A and B, rotation matrices
    (*bs, 3, 3) broadcast together -> (*bs,)."""
    from scipy.spatial.transform import Rotation

    rel = np.einsum("...ab,...cb->...ac", A, B)
    angle = Rotation.from_matrix(rel.reshape(-1, 3, 3)).magnitude()
    return np.degrees(angle).reshape(rel.shape[:-2])


def se3_log(T: np.ndarray) -> np.ndarray:
    """Rigid transforms (*bs, 4, 4) -> twists (*bs, 6): rotation vector ω then v, such that
    T = exp([ω, v]) (MR eq. 3.88: p = G(ω) v with G = I + b W + c W²), so that exp(s·ξ)
    moves along the same screw by the fraction s (model/se3.apply_se3 applies it)."""
    T = np.asarray(T, np.float64)
    w = matrix_to_rotvec(T[..., :3, :3])
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    small = theta < 1e-6
    t = np.where(small, 1.0, theta)
    b = np.where(small, 0.5 - theta ** 2 / 24, (1 - np.cos(t)) / t ** 2)
    c = np.where(small, 1.0 / 6 - theta ** 2 / 120, (t - np.sin(t)) / t ** 3)
    W = np.zeros(w.shape[:-1] + (3, 3))
    W[..., 0, 1], W[..., 0, 2], W[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    W = W - np.swapaxes(W, -1, -2)
    G = np.eye(3) + b * W + c * (W @ W)
    v = np.linalg.solve(G, T[..., :3, 3:])[..., 0]
    return np.concatenate([w, v], -1)


def euler_head(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """Rotation (3, 3) of a head in its own axes (x: the subject's left, y: up, z: out of
    the face): yaw > 0 turns the face towards +x, pitch > 0 raises the chin (looks up),
    roll > 0 tilts the top of the head towards +x; applied roll, then pitch, then yaw."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("YXZ", [yaw_deg, -pitch_deg, -roll_deg], degrees=True
                               ).as_matrix()


def head_euler(R: np.ndarray) -> np.ndarray:
    """The inverse of `euler_head`: rotations (..., 3, 3) in the head's own axes ->
    (..., 3) yaw, pitch, roll in degrees."""
    from scipy.spatial.transform import Rotation

    yxz = Rotation.from_matrix(np.asarray(R, np.float64).reshape(-1, 3, 3)).as_euler(
        "YXZ", degrees=True)
    return (yxz * [1.0, -1.0, -1.0]).reshape(*np.shape(R)[:-2], 3)


def quat_wxyz_to_matrix(wxyz: np.ndarray) -> np.ndarray:
    """A quaternion (w, x, y, z), any norm -> its rotation matrix (3, 3)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.asarray(wxyz, np.float64), scalar_first=True).as_matrix()


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation (3, 3) taking direction a (3,) to direction b (3,) (Rodrigues;
    not for opposite directions, where any half turn would do)."""
    a = np.asarray(a, np.float64) / np.linalg.norm(a)
    b = np.asarray(b, np.float64) / np.linalg.norm(b)
    K = skew(np.cross(a, b))
    s2 = float(np.sum(np.cross(a, b) ** 2))
    return np.eye(3) + K + K @ K * ((1 - float(a @ b)) / s2 if s2 > 1e-24 else 0.5)


def is_rigid(m: np.ndarray, tol: float) -> np.ndarray:
    """Whether 4x4 matrices m (..., 4, 4) are rigid transforms: an orthonormal rotation with
    det +1 and a last row 0 0 0 1, each within `tol`. -> (...) bool."""
    R = m[..., :3, :3]
    off = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max((-1, -2))
    last = np.abs(m[..., 3, :] - [0, 0, 0, 1]).max(-1)
    return (off <= tol) & (last <= tol) & (np.linalg.det(R) > 0)


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising Σ |s R src + t - dst|² over points src, dst (N, 3)
    (Umeyama 1991)."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    if np.linalg.det(U @ Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (a * a).sum(1).mean())
    return s, R, md - s * R @ ms


# ----------------------------------------------------------------------------- cameras


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 1.0, 0.0),
            roll_deg: float = 0.0) -> np.ndarray:
    """Camera-to-world (4, 4), OpenGL axes, at `eye` looking at `target` with `up` roughly
    up, then rolled by `roll_deg` about its viewing axis."""
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    back = eye - target
    back = back / np.linalg.norm(back)
    right = np.cross(up, back)
    if np.linalg.norm(right) < 1e-9:  # looking along `up`: any perpendicular will do
        right = np.cross([1.0, 0.0, 0.0] if abs(back[0]) < 0.9 else [0.0, 1.0, 0.0], back)
    right = right / np.linalg.norm(right)
    cam_up = np.cross(back, right)
    if roll_deg:
        c, s = np.cos(np.deg2rad(roll_deg)), np.sin(np.deg2rad(roll_deg))
        right, cam_up = c * right + s * cam_up, -s * right + c * cam_up
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, cam_up, back, eye
    return c2w


def project(points_cam: Array, fx, fy, cx: float, cy: float,
            min_depth: float | None = None) -> Array:
    """Pinhole projection of camera-space points (..., 3), NumPy or torch -> pixels (..., 2).

    Depth -z is the divisor. `min_depth` clamps it from below, which an optimiser needs when
    points stray behind the camera; without it only depths within 1e-9 of zero are
    replaced (points behind the camera keep their sign). fx, fy may be tensors (a focal
    length being optimised)."""
    if isinstance(points_cam, np.ndarray):
        xp = np
    else:
        import torch as xp
    z = -points_cam[..., 2]
    if min_depth is not None:
        z = xp.where(z < min_depth, min_depth, z)
    else:
        z = xp.where(xp.abs(z) < 1e-9, 1e-9, z)
    return xp.stack([fx * points_cam[..., 0] / z + cx, cy - fy * points_cam[..., 1] / z], -1)


def project_points(points: np.ndarray, intr: Pinhole, c2w: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) -> pixel coordinates (N, 2) (x right, y down) and z-depth (N,)."""
    w2c = np.linalg.inv(c2w)
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    return project(pc, intr.fx, intr.fy, intr.cx, intr.cy), -pc[:, 2]


# ----------------------------------------------------------------------------- regions


def ellipsoid_weight(x: Tensor, centre: Tensor, axes: Tensor, radii: Tensor, band: float
                     ) -> Tensor:
    """A soft ellipsoidal region: 1 inside the ellipsoid (centre (3,), semi-axes `radii`
    (3,) along the columns of `axes` (3, 3)), a smoothstep down to 0 at 1 + band times its
    radius. x (*bs, 3) -> (*bs,)."""
    q = ((x - centre) @ axes) / radii
    s = ((1 + band - q.norm(dim=-1)) / band).clamp(0, 1)
    return s * s * (3 - 2 * s)
