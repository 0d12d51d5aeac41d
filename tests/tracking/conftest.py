"""Fixtures for the tracking tests: the landmarker model and a tiny model in FLAME's file
format (the test videos are tests/media.py's).

The landmarker model is never skipped: CI runs scripts/get_landmarker.py first, and a
missing model must fail these tests loudly.
"""

from __future__ import annotations

import pickle
import sys
import types
from pathlib import Path

import numpy as np
import pytest

SETUP = "python scripts/get_landmarker.py"


@pytest.fixture(scope="session")
def landmarker_path() -> Path:
    from flamenerf.errors import UserError
    from flamenerf.tracking.landmarker import find_model

    try:
        return find_model()
    except UserError as e:
        pytest.fail(f"face_landmarker.task is not installed ({e}). Run `{SETUP}` first.",
                    pytrace=False)


@pytest.fixture(scope="session")
def canonical_mesh(landmarker_path):
    from flamenerf.tracking.landmarker import load_canonical_mesh

    return load_canonical_mesh(landmarker_path)


# ----------------------------------------------------------------------------- tiny FLAME


class _FakeCh:
    """Pickles like chumpy.ch.Ch (module and class name, state dict with 'x')."""

    def __init__(self, x):
        self.x = x

    def __reduce__(self):
        import copyreg

        return (copyreg._reconstructor, (_FakeCh, object, None), {"x": self.x})


def _pickle_with_fake_chumpy(obj, path: Path) -> None:
    mod_ch = types.ModuleType("chumpy.ch")
    _FakeCh.__module__, _FakeCh.__qualname__, _FakeCh.__name__ = "chumpy.ch", "Ch", "Ch"
    mod_ch.Ch = _FakeCh
    saved = {k: sys.modules.get(k) for k in ("chumpy", "chumpy.ch")}
    sys.modules["chumpy"] = types.ModuleType("chumpy")
    sys.modules["chumpy.ch"] = mod_ch
    try:
        with open(path, "wb") as f:
            pickle.dump(obj, f, protocol=2)
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v


def make_tiny_flame(d: Path, canonical, num_shape: int = 6, num_expr: int = 6,
                    seed: int = 0) -> dict:
    """A FLAME-format model built on MediaPipe's canonical mesh (so that the embedding is
    exact), in a frame rotated and shifted from the head frame, plus its embedding.
    Expression component 0 opens the jaw region; the others are smooth random fields."""
    import scipy.sparse

    rng = np.random.default_rng(seed)
    X = canonical.vertices  # (468, 3) metres
    ang = np.radians(8.0)
    Rf = np.array([[1, 0, 0], [0, np.cos(ang), -np.sin(ang)], [0, np.sin(ang), np.cos(ang)]])
    v = X @ Rf.T + np.array([0.0, -0.02, -0.03])  # FLAME frame != head frame
    V = len(v)
    y = v[:, 1]
    lo = y < np.percentile(y, 25)  # chin and lower lip

    def bump():  # a local deformation: Gaussian bump of 2 cm radius, 3 mm tall
        c = v[rng.integers(V)]
        g = np.exp(-((v - c) ** 2).sum(1) / (2 * 0.02**2))
        return g[:, None] * rng.normal(0, 0.003, 3)

    shapedirs = np.zeros((V, 3, num_shape + num_expr))
    for k in range(num_shape):
        shapedirs[:, :, k] = bump()
    jaw_open = np.zeros((V, 3))
    jaw_open[lo, 1] = -0.004 * (np.percentile(y, 25) - y[lo]) / np.ptp(y[lo])
    shapedirs[:, :, num_shape] = jaw_open
    for k in range(1, num_expr):
        shapedirs[:, :, num_shape + k] = bump()
    J = np.zeros((5, V))
    J[0] = 1.0 / V
    neck = y < np.percentile(y, 10)
    J[1, neck] = 1.0 / neck.sum()
    jaw_c = lo & (np.abs(v[:, 0]) < 0.03)
    J[2, jaw_c] = 1.0 / jaw_c.sum()
    for j, sgn in ((3, 1), (4, -1)):
        eye = np.argsort(np.abs(v[:, 0] - sgn * 0.03) + np.abs(y - 0.03))[:6]
        J[j, eye] = 1.0 / 6
    W = np.zeros((V, 5))
    W[:, 1] = 1.0
    W[lo, 1], W[lo, 2] = 0.3, 0.7
    model = {
        "v_template": v, "shapedirs": _FakeCh(shapedirs),
        "posedirs": rng.normal(0, 1e-5, (V, 3, 36)),
        "J_regressor": scipy.sparse.csc_matrix(J), "weights": W,
        "kintree_table": np.array([[2**32 - 1, 0, 1, 1, 1], [0, 1, 2, 3, 4]], np.int64),
        "f": canonical.faces.astype(np.uint32), "bs_style": "lbs", "bs_type": "lrotmin",
    }
    d.mkdir(parents=True, exist_ok=True)
    _pickle_with_fake_chumpy(model, d / "generic_model.pkl")
    ids = np.arange(0, 468, 6)
    faces = canonical.faces
    lf, lb = [], []
    for j in ids:
        fi = int(np.flatnonzero((faces == j).any(1))[0])
        lf.append(fi)
        lb.append((faces[fi] == j).astype(np.float64))
    np.savez(d / "mediapipe_landmark_embedding.npz", lmk_face_idx=np.array(lf),
             lmk_b_coords=np.array(lb), landmark_indices=ids)
    return {"dir": d, "num_shape": num_shape, "num_expr": num_expr, "R": Rf}


@pytest.fixture(scope="session")
def tiny_flame(tmp_path_factory, canonical_mesh) -> dict:
    return make_tiny_flame(tmp_path_factory.mktemp("flame") / "FLAME", canonical_mesh)
