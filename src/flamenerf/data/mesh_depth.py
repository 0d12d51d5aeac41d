"""The face mesh rasterised: which triangle each pixel sees (the spatial prior's silhouette,
data/prior.py) and how deep it lies along the pixel's ray (the face-depth prior's target in
training, `train.face_depth_weight`)."""

from __future__ import annotations

import numpy as np

from flamenerf.geometry import Pinhole, project_points


def triangle_ids(vertices: np.ndarray, faces: np.ndarray, intr: Pinhole, c2w: np.ndarray,
                 w: int, h: int) -> np.ndarray:
    """Which triangle each pixel sees: triangles drawn far to near by their mean depth (the
    painter's algorithm: where a face mesh's small triangles overlap on screen, one lies
    clearly behind the other, as the nose before the cheek).

    vertices (V, 3) world; faces (F, 3) int -> (h, w) int32, −1 where no triangle is.
    """
    from PIL import Image, ImageDraw

    uv, z = project_points(np.asarray(vertices, np.float64), intr, c2w)
    faces = np.asarray(faces)
    zf = z[faces]
    order = np.argsort(-zf.mean(axis=1))
    order = order[(zf[order] > 1e-6).all(axis=1)]
    img = Image.new("I", (w, h), -1)
    draw = ImageDraw.Draw(img)
    # the corners as flat Python lists made in one call: converting them triangle by
    # triangle was most of a 128 px silhouette's 9 ms (now 2, the same pixels)
    corners = uv[faces[order]].reshape(len(order), 6).tolist()
    for xy, f in zip(corners, order.tolist()):
        draw.polygon(xy, fill=f)
    return np.asarray(img, np.int32)


def mesh_depth(vertices: np.ndarray, faces: np.ndarray, intr: Pinhole, c2w: np.ndarray,
               dirs_cam: np.ndarray) -> np.ndarray:
    """z-depth of the face mesh through each pixel.

    vertices (V, 3) world; faces (F, 3) int; dirs_cam (H, W, 3): the pixels' camera-space
    ray directions with unit −z component (data/rays.py), so the ray parameter is z-depth.
    -> (H, W) float32, inf where the ray misses the mesh.
    """
    h, w = dirs_cam.shape[:2]
    ids = triangle_ids(vertices, faces, intr, c2w, w, h)
    out = np.full((h, w), np.inf, np.float32)
    hit = ids >= 0
    if not hit.any():
        return out
    w2c = np.linalg.inv(c2w)
    vc = np.asarray(vertices, np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
    tri = vc[np.asarray(faces)[ids[hit]]]  # (P, 3, 3) camera space
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    d = dirs_cam[hit].astype(np.float64)
    den = (n * d).sum(-1)
    t = (n * tri[:, 0]).sum(-1) / np.where(np.abs(den) > 1e-12, den, np.nan)
    out[hit] = np.where(np.isfinite(t) & (t > 0), t, np.inf)
    return out
