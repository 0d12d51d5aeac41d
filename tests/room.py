"""A tiny textured room seen from known cameras with a head moving in it: ground truth for
the background camera solve (tests/tracking/test_world.py).

The room is a box (walls, floor and ceiling) textured with scikit-image photographs, so SIFT
finds features at every depth; the head is a grey sphere (the person mask covers it) and its
landmarks are MediaPipe's canonical face posed by the head's world-from-head matrix.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flamenerf.data.dataset import Intrinsics
from flamenerf.geometry import look_at, project_points

# (normal axis, coordinate, texture): walls of the box [-1.2, 1.2] x [-0.8, 0.9] x [-2.5, 1]
WALLS = ((2, -1.6, "astronaut"), (0, -0.9, "coffee"), (0, 0.9, "chelsea"),
         (1, -0.7, "rocket"), (1, 0.7, "immunohistochemistry"), (2, 1.0, "astronaut"))


@dataclass
class Room:
    frames: list[np.ndarray]  # (H, W, 3) uint8
    c2w: np.ndarray  # (N, 4, 4) OpenGL, world metres
    head_pose: np.ndarray  # (N, 4, 4) world-from-head
    landmarks: np.ndarray  # (N, 478, 3) pixels (+ relative depth), only 468 meaningful
    intr: Intrinsics
    moving: np.ndarray | None = None  # (N, H, W) bool: the swaying patch, when there is one


def _textures() -> dict[str, np.ndarray]:
    from skimage import data

    tex = {name: np.asarray(getattr(data, name)(), np.float32)[..., :3]
           for name in {w[2] for w in WALLS}}
    tex["grass"] = np.asarray(data.grass(), np.float32)[..., None]  # the swaying leaves
    return tex


def _yaw_pitch(yaw: float, pitch: float) -> np.ndarray:
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    return Ry @ Rx


def render_room(canonical: np.ndarray, n: int = 16, size: tuple[int, int] = (192, 144),
                fov: float = 60.0, camera_deg: float = 30.0, head_yaw_deg: float = 20.0,
                head_shift: float = 0.03, radius: float = 0.1, textured: bool = True,
                shake_deg: float = 0.0, sway: bool = False, seed: int = 0) -> Room:
    """Camera on an arc of `camera_deg` around the head at 0.6 m; the head yaws by
    ±head_yaw_deg, pitches by half that and shifts by head_shift metres, independently.
    textured=False: plain walls (a smooth shading only). shake_deg: a hand's shake on top,
    the camera turning about its own centre by a smooth random walk of up to about this
    much. sway: a patch of the back wall whose texture moves by itself (leaves in wind)."""
    W, H = size
    f = 0.5 * W / np.tan(np.radians(fov) / 2)
    intr = Intrinsics(W, H, f, f, W / 2, H / 2)
    tex = _textures()
    if not textured:  # a smooth gradient: shading without anything SIFT can latch onto
        tex = {k: np.broadcast_to(np.linspace(90, 160, 64, dtype=np.float32)[:, None, None],
                                  (64, 64, 3)).copy() for k in tex}
    t = np.linspace(0.0, 1.0, n)
    az = np.radians(camera_deg) * (t - 0.5)
    centre = np.array([0.0, 0.0, -0.5])
    yaw = np.radians(head_yaw_deg) * np.sin(2 * np.pi * t)
    pitch = 0.5 * np.radians(head_yaw_deg) * np.sin(4 * np.pi * t + 1.0)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64) + 0.5
    dirs_cam = np.stack([(xx - W / 2) / f, -(yy - H / 2) / f, -np.ones_like(xx)], -1)
    frames, c2ws, poses, lms = [], [], [], []
    shake = _shake(n, shake_deg, seed)
    masks = []
    for k in range(n):
        eye = centre + 0.6 * np.array([np.sin(az[k]), 0.05, np.cos(az[k])])
        c2w = look_at(eye, centre)
        c2w[:3, :3] = c2w[:3, :3] @ shake[k]
        pose = np.eye(4)
        pose[:3, :3] = _yaw_pitch(yaw[k], pitch[k])
        pose[:3, 3] = centre + head_shift * np.array([np.sin(3 * t[k]), 0.3 * t[k], 0.0])
        d = dirs_cam.reshape(-1, 3) @ c2w[:3, :3].T
        img, moving = _trace(eye, d, tex, t[k] if sway else None)
        img = img.reshape(H, W, 3)
        # the head: a sphere around the head origin, shaded so it is not a flat disc
        oc = eye - pose[:3, 3]
        b = d @ oc
        disc = b * b - (d * d).sum(-1) * (oc @ oc - radius**2)
        hit = (disc > 0).reshape(H, W)
        img[hit] = 170.0 + 40.0 * dirs_cam[hit][:, 0:1]
        masks.append(moving.reshape(H, W) & ~hit)
        frames.append(img.clip(0, 255).astype(np.uint8))
        X = canonical @ pose[:3, :3].T + pose[:3, 3]
        uv, z = project_points(X, intr, c2w)
        L = np.zeros((478, 3))
        L[:468, :2] = uv
        L[:468, 2] = (z - z.mean()) * f / z.mean()
        L[468:, :2] = uv[:10]  # iris points: anywhere on the face
        lms.append(L)
        c2ws.append(c2w)
        poses.append(pose)
    return Room(frames, np.stack(c2ws), np.stack(poses), np.stack(lms), intr,
                np.stack(masks) if sway else None)


def _shake(n: int, deg: float, seed: int) -> np.ndarray:
    """Rotations (n, 3, 3) of a hand's shake: a smoothed random walk, largest turn ~deg."""
    from scipy.ndimage import gaussian_filter1d
    from scipy.spatial.transform import Rotation

    if deg == 0:
        return np.tile(np.eye(3), (n, 1, 1))
    w = gaussian_filter1d(np.random.default_rng(seed).normal(0, 1, (n, 3)), 2.0, axis=0)
    w = np.cumsum(w, 0)
    w -= w.mean(0)
    w *= np.radians(deg) / np.abs(w).max()
    return Rotation.from_rotvec(w).as_matrix()


SWAY_BOX = (0.25, 0.85, -0.3, 0.5)  # x0, x1, y0, y1 of the swaying patch on the back wall


def _trace(eye: np.ndarray, d: np.ndarray, tex: dict[str, np.ndarray],
           sway_t: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Colour of the first wall each ray (M, 3) from `eye` hits, and whether it hit the
    swaying patch (when sway_t, the time in 0..1, is given)."""
    from scipy.ndimage import map_coordinates

    best = np.full(len(d), np.inf)
    out = np.zeros((len(d), 3), np.float32)
    patch = np.zeros(len(d), bool)
    lo = np.array([-0.9, -0.7, -1.6])
    hi = np.array([0.9, 0.7, 1.0])
    for axis, coord, name in WALLS:
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (coord - eye[axis]) / d[:, axis]
        p = eye + s[:, None] * d
        a, b = [i for i in range(3) if i != axis]
        ok = (s > 0) & (s < best)
        if not ok.any():
            continue
        img = tex[name]
        pa, pb = p[ok, a], p[ok, b]
        u = (pa - lo[a]) / (hi[a] - lo[a]) * (img.shape[1] - 1)
        v = (hi[b] - pb) / (hi[b] - lo[b]) * (img.shape[0] - 1)
        best[ok] = s[ok]
        out[ok] = np.stack([map_coordinates(img[..., c], [v, u], order=1, mode="reflect")
                            for c in range(3)], -1)
        patch[ok] = False
        if sway_t is not None and axis == 2 and coord < 0:  # the back wall
            x0, x1, y0, y1 = SWAY_BOX
            inside = (pa > x0) & (pa < x1) & (pb > y0) & (pb < y1)
            # leaves in the wind: their texture slides back and forth, unlike the wall's
            la = pa[inside] + 0.04 * np.sin(2 * np.pi * (3 * sway_t + 2 * pb[inside]))
            leaves = tex["grass"]
            lu = (la - x0) / (x1 - x0) * (leaves.shape[1] - 1)
            lv = (y1 - pb[inside]) / (y1 - y0) * (leaves.shape[0] - 1)
            grey = map_coordinates(leaves[..., 0], [lv, lu], order=1, mode="reflect")
            idx = np.flatnonzero(ok)[inside]
            out[idx] = grey[:, None] * np.array([0.5, 0.9, 0.4], np.float32)
            patch[idx] = True
    return out, patch
