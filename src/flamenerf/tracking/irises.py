"""The irises as vertices of the tracked face mesh.

MediaPipe's 478 landmarks end with ten iris points (468-477: each iris's centre and four
points on its rim) that its 898 triangles leave out, and the mesh solve (tracking/cameras)
fits the 468 that the triangles hold. Without the irises a gaze moves no vertex: the
β -> mesh model gives the eyeLook controls no place on the face, the per-control prior no
region and the mesh guide nothing to carry. Each iris point is put on the solved mesh
where the landmarker sees it: inside the triangles that close its own eye's opening (their
vertices are the eye's contour, 16 per eye), at the same barycentric coordinates as in the
image; a rim point hidden under a lid goes to the nearest point of the opening (with any
triangle allowed, one went to the other eye). No triangle holds them, so silhouettes and
depth are as before; the vertex count becomes 478, MediaPipe's full topology.
"""

from __future__ import annotations

import numpy as np

from flamenerf.tracking.landmarker import NUM_LANDMARKS, NUM_MESH_VERTICES, part_outlines

# MediaPipe's iris points 468-472 are the right eye's, 473-477 the left's (centre first)
IRIS_FIRST, IRIS_COUNT = NUM_MESH_VERTICES, NUM_LANDMARKS - NUM_MESH_VERTICES


def eye_triangles(faces: np.ndarray, eye: int | None = None) -> np.ndarray:
    """The triangles (F, 3) whose three vertices lie on one eye's contour (MediaPipe's
    outline of the lids, `landmarker.part_outlines`; `eye`: 0 the subject's left, 1 the
    right, None both): those that close the eye's opening. -> (T, 3)"""
    eyes = part_outlines()["eyes"]
    contours = eyes if eye is None else (eyes[eye],)
    out = [f for contour in map(set, contours) for f in faces
           if all(int(v) in contour for v in f)]
    return np.asarray(out, np.int64).reshape(-1, 3)


def closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """The closest point to p (..., 2) on each triangle a, b, c (..., 2) (broadcast), as
    barycentric weights (..., 3) and its distance (...,): p's own coordinates where the
    triangle holds it, else the nearest point of its edges (so a thin triangle, a closed
    eye's, gives sensible weights too)."""
    p, a, b, c = np.broadcast_arrays(p, a, b, c)
    corners = np.stack([a, b, c], -2)  # (..., 3, 2)
    best_w = np.zeros(corners.shape[:-1])
    best_d = np.full(corners.shape[:-2], np.inf)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        e = corners[..., j, :] - corners[..., i, :]
        t = ((p - corners[..., i, :]) * e).sum(-1) / np.maximum((e * e).sum(-1), 1e-24)
        t = np.clip(t, 0.0, 1.0)
        d = np.linalg.norm(corners[..., i, :] + t[..., None] * e - p, axis=-1)
        w = np.zeros_like(best_w)
        w[..., i], w[..., j] = 1 - t, t
        closer = d < best_d
        best_d = np.where(closer, d, best_d)
        best_w = np.where(closer[..., None], w, best_w)
    v0, v1, v2 = corners[..., 1, :] - a, corners[..., 2, :] - a, p - a
    den = v0[..., 0] * v1[..., 1] - v1[..., 0] * v0[..., 1]
    ok = np.abs(den) > 1e-12
    den = np.where(ok, den, 1.0)
    u = (v2[..., 0] * v1[..., 1] - v1[..., 0] * v2[..., 1]) / den
    v = (v0[..., 0] * v2[..., 1] - v2[..., 0] * v0[..., 1]) / den
    inside = ok & (u >= 0) & (v >= 0) & (u + v <= 1)
    w_in = np.stack([1 - u - v, u, v], -1)
    return (np.where(inside[..., None], w_in, best_w), np.where(inside, 0.0, best_d))


def iris_vertices(landmarks: np.ndarray, vertices: np.ndarray, faces: np.ndarray
                  ) -> np.ndarray:
    """The ten iris points on each frame's solved mesh.

    landmarks (N, 478, >=2): the landmarker's image points; vertices (N, 468, 3): the
    solved meshes; faces (F, 3): MediaPipe's triangles. Each iris point takes the triangle
    of its own eye that holds it in the image, or, outside the opening (a rim point under
    a lid, any point of a closed eye), the nearest point of that eye's triangles.
    -> (N, 10, 3)"""
    out = []
    for eye, first in ((1, IRIS_FIRST), (0, IRIS_FIRST + IRIS_COUNT // 2)):
        tri = eye_triangles(faces, eye)
        if len(tri) == 0:
            raise ValueError("no triangles close the eyes: not MediaPipe's face mesh")
        p = landmarks[:, first:first + IRIS_COUNT // 2, None, :2]  # (N, 5, 1, 2)
        corners = [landmarks[:, None, tri[:, j], :2] for j in range(3)]  # (N, 1, T, 2)
        w, d = closest_on_triangles(p, *corners)  # (N, 5, T, 3), (N, 5, T)
        best = d.argmin(-1)  # (N, 5)
        w = np.take_along_axis(w, best[..., None, None], 2)[:, :, 0]  # (N, 5, 3)
        xyz = np.take_along_axis(vertices[:, None], tri[best][..., None], 2)  # (N, 5, 3, 3)
        out.append(np.einsum("nkj,nkjd->nkd", w, xyz))
    return np.concatenate(out, 1)


def with_irises(vertices: np.ndarray, landmarks: np.ndarray, faces: np.ndarray
                ) -> np.ndarray:
    """vertices (N, 468, 3) -> (N, 478, 3) with `iris_vertices` appended; unchanged when
    the landmarks have no irises (fewer than 478 points)."""
    if landmarks.shape[1] < IRIS_FIRST + IRIS_COUNT:
        return vertices
    irises = iris_vertices(landmarks, vertices, faces).astype(vertices.dtype)
    return np.concatenate([vertices, irises], 1)
