"""Cameras of the viewer: viser's browser camera <-> the renderer's OpenGL camera-to-world.

viser reports each browser's camera as a world-from-camera rotation `wxyz` (OpenCV axes:
x right, y down, looking down +z), a position, a vertical field of view in radians and
the canvas aspect ratio. The renderer wants a camera-to-world 4x4 with OpenGL axes (x
right, y up, looking down -z) and pinhole intrinsics in pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from flamenerf.data.dataset import Dataset, Intrinsics, reference_position
from flamenerf.geometry import quat_wxyz_to_matrix

_CV_TO_GL = np.diag([1.0, -1.0, -1.0])


def c2w_from_viser(wxyz: np.ndarray, position: np.ndarray) -> np.ndarray:
    """viser camera (OpenCV axes) -> (4, 4) camera-to-world with OpenGL axes."""
    c2w = np.eye(4)
    c2w[:3, :3] = quat_wxyz_to_matrix(wxyz) @ _CV_TO_GL
    c2w[:3, 3] = np.asarray(position, np.float64)
    return c2w


def view_intrinsics(fov_y: float, aspect: float, height: int) -> Intrinsics:
    """A centred pinhole camera `height` pixels tall with the browser's field of view and
    aspect ratio, so that the image exactly covers the canvas it is shown on."""
    h = max(1, int(height))
    w = max(1, round(h * aspect))
    f = 0.5 * h / math.tan(0.5 * fov_y)
    return Intrinsics(w, h, f, f, w / 2.0, h / 2.0)


@dataclass
class HomeCamera:
    """Where the viewer starts: the dataset's frame-0 camera, orbiting the scene centre."""

    c2w: np.ndarray  # (4, 4) OpenGL axes
    position: np.ndarray  # (3,)
    look_at: np.ndarray  # (3,) on frame 0's optical axis, level with the face
    up: np.ndarray  # (3,) frame 0's up axis
    fov_y: float  # radians, the dataset camera's vertical field of view
    frame_position: int  # index into ds.frames of the frame with code 0




def home_camera(ds: Dataset, position: int | None = None) -> HomeCamera:
    """Frame 0's camera (the frame whose codes the viewer renders), or with `position` the
    camera of that frame of `ds.frames` (a frame shown as filmed, from where it was)."""
    pos = reference_position(ds) if position is None else int(position)
    c2w = np.asarray(ds.frames[pos].c2w, np.float64)
    eye = c2w[:3, 3]
    forward = -c2w[:3, 2]
    forward = forward / np.linalg.norm(forward)
    # The scene centre is the face: orbit around the point of the frame's optical axis
    # nearest to its face mesh's centroid, so the first view is exactly the frame's.
    centre = ds.face_vertices[pos].reshape(-1, 3).mean(0).astype(np.float64)
    dist = float(np.dot(centre - eye, forward))
    if not np.isfinite(dist) or dist <= 1e-3:
        dist = 0.5 * (ds.near + ds.far)
    intr = ds.intrinsics
    fov_y = 2.0 * math.atan(0.5 * intr.h / intr.fy)
    up = c2w[:3, 1] / np.linalg.norm(c2w[:3, 1])
    return HomeCamera(c2w, eye.copy(), eye + dist * forward, up, fov_y, pos)
