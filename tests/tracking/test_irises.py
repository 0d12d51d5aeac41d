"""The irises put on the solved face mesh (tracking/irises.py)."""

from __future__ import annotations

import numpy as np
import pytest

from flamenerf.tracking.irises import (IRIS_COUNT, closest_on_triangles, eye_triangles,
                                       iris_vertices, with_irises)


def _project(v: np.ndarray, R: np.ndarray) -> np.ndarray:
    """A weak-perspective view of vertices (V, 3): rotated, scaled to pixels. -> (V, 2)"""
    return 2000.0 * (v @ R.T)[:, :2] + 256.0


def test_eye_triangles_close_both_eyes(canonical_mesh):
    tri = eye_triangles(canonical_mesh.faces)
    assert tri.shape == (28, 3)  # a 16-gon per eye
    assert eye_triangles(canonical_mesh.faces, 0).shape == (14, 3)
    assert eye_triangles(np.array([[0, 1, 2], [33, 7, 0]])).shape == (0, 3)


def test_irises_land_where_the_image_sees_them(canonical_mesh):
    """Iris points projected from places on the eyes' triangles (turned, expressive faces:
    vertices moved) come back on the mesh where they project onto the image points (the
    place itself where no other triangle of the eye overlaps it in the image)."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    faces = canonical_mesh.faces
    right, left = eye_triangles(faces, 1), eye_triangles(faces, 0)  # 468-472, 473-477
    N = 4
    verts = canonical_mesh.vertices[None] + rng.normal(0, 3e-4, (N, 468, 3))
    lms, truth, rots = [], [], []
    for n in range(N):
        R = Rotation.from_euler("xyz", rng.uniform(-20, 20, 3), degrees=True).as_matrix()
        pick = np.concatenate([right[rng.integers(len(right), size=5)],
                               left[rng.integers(len(left), size=5)]])
        w = rng.dirichlet(np.ones(3), IRIS_COUNT)
        p3 = np.einsum("kj,kjd->kd", w, verts[n][pick])
        truth.append(p3)
        rots.append(R)
        lms.append(np.concatenate([_project(verts[n], R), _project(p3, R)]))
    got = iris_vertices(np.stack(lms), verts, faces)
    assert got.shape == (N, IRIS_COUNT, 3)
    for n in range(N):
        np.testing.assert_allclose(_project(got[n], rots[n]), lms[n][468:], atol=1e-6)
    exact = np.isclose(got, np.stack(truth), atol=1e-6).all(-1)
    assert exact.mean() > 0.9


def test_an_iris_point_outside_the_opening_goes_onto_its_own_eye(canonical_mesh):
    """Rim points hidden by the lids (outside every eye triangle in the image, here above
    the upper lid's middle) go to the nearest point of their own eye's opening: the lid's
    edge, not a triangle of the other eye."""
    v = canonical_mesh.vertices[None].astype(np.float64)
    lm2 = _project(v[0], np.eye(3))
    lid = {"right": 159, "left": 386}  # the upper lids' middles (this view: y up)
    iris2 = np.concatenate([np.repeat(lm2[[lid[side]]] + np.array([[0.0, 30.0]]), 5, 0)
                            for side in ("right", "left")])
    got = iris_vertices(np.concatenate([lm2, iris2])[None], v, canonical_mesh.faces)[0]
    np.testing.assert_allclose(got[:5], np.repeat(v[0, [159]], 5, 0), atol=1e-9)
    np.testing.assert_allclose(got[5:], np.repeat(v[0, [386]], 5, 0), atol=1e-9)


def test_with_irises_appends_or_leaves_alone(canonical_mesh):
    v = canonical_mesh.vertices[None].astype(np.float32)
    lm = np.concatenate([_project(v[0], np.eye(3)), _project(v[0, [33] * IRIS_COUNT],
                                                             np.eye(3))])[None]
    out = with_irises(v, lm, canonical_mesh.faces)
    assert out.shape == (1, 478, 3) and out.dtype == np.float32
    np.testing.assert_array_equal(out[:, :468], v)
    np.testing.assert_allclose(out[0, 468], v[0, 33], atol=1e-6)
    assert with_irises(v, lm[:, :468], canonical_mesh.faces) is v


def test_closest_point_on_triangles():
    a, b, c = np.array([0.0, 0.0]), np.array([2.0, 0.0]), np.array([0.0, 2.0])
    w, d = closest_on_triangles(np.array([0.5, 0.5]), a, b, c)  # inside
    np.testing.assert_allclose(w, [0.5, 0.25, 0.25])
    np.testing.assert_allclose(d, 0)
    w, d = closest_on_triangles(np.array([1.0, -1.0]), a, b, c)  # below the edge a-b
    np.testing.assert_allclose(w, [0.5, 0.5, 0.0])
    np.testing.assert_allclose(d, 1.0)
    w, d = closest_on_triangles(np.array([1.0, 1.0]), a, a, b)  # a closed eye: a segment
    assert np.all(np.isfinite(w)) and np.isclose(d, 1.0) and np.isclose(w.sum(), 1.0)
    with pytest.raises(ValueError, match="eyes"):
        iris_vertices(np.zeros((1, 478, 2)), np.zeros((1, 468, 3)), np.zeros((5, 3), int))
