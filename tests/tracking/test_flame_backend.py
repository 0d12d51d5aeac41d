"""FLAME backend: loading FLAME's file format safely, the skinning model, and the fit."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from flamenerf.errors import UserError
from flamenerf.tracking.flame import FlameLayer, fit_flame, load_flame_dir


def test_loads_flame_format_with_sparse_and_chumpy(tiny_flame):
    m = load_flame_dir(tiny_flame["dir"])
    assert m.v_template.shape == (468, 3)
    assert m.shapedirs.shape == (468, 3, tiny_flame["num_shape"])  # first half: shape
    assert m.exprdirs.shape == (468, 3, tiny_flame["num_expr"])
    assert m.J_regressor.shape == (5, 468) and m.parents.tolist() == [-1, 0, 1, 1, 1]
    assert len(m.lmk_faces) == len(m.lmk_mediapipe) == 78


def test_refuses_code_in_pickles(tmp_path, tiny_flame):
    import shutil

    d = tmp_path / "evil"
    shutil.copytree(tiny_flame["dir"], d)

    class Evil:
        def __reduce__(self):
            import os

            return (os.system, ("echo pwned > " + str(tmp_path / "pwned"),))

    with open(d / "generic_model.pkl", "wb") as f:
        pickle.dump({"v_template": Evil()}, f)
    with pytest.raises(UserError, match="refusing to load"):
        load_flame_dir(d)
    assert not (tmp_path / "pwned").exists()


def test_missing_files_are_one_clear_error(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        load_flame_dir(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="no FLAME model"):
        load_flame_dir(tmp_path / "empty")


def test_skinning_rest_pose_and_jaw(tiny_flame):
    m = load_flame_dir(tiny_flame["dir"])
    layer = FlameLayer(m, 6, 6)
    z = torch.zeros
    shape = torch.tensor(np.linspace(-1, 1, 6))
    v0 = layer(shape, z(1, 6, dtype=torch.float64), z(1, 5, 3, dtype=torch.float64))[0]
    want = m.v_template + m.shapedirs @ shape.numpy()
    np.testing.assert_allclose(v0.numpy(), want, atol=1e-9)  # zero pose: blend shapes only
    pose = z(1, 5, 3, dtype=torch.float64)
    pose[0, 2, 0] = 0.3  # open the jaw
    v1 = layer(shape, z(1, 6, dtype=torch.float64), pose)[0].numpy()
    moved = np.linalg.norm(v1 - v0.numpy(), axis=1) > 1e-4
    assert moved.any()
    assert np.all(m.weights[moved, 2] > 0)  # only jaw-weighted vertices move


@pytest.mark.slow
def test_fit_recovers_expression_from_landmarks(tiny_flame, canonical_mesh):
    """Synthetic landmarks from known FLAME parameters and cameras -> the fit finds them."""
    from types import SimpleNamespace

    from flamenerf.geometry import so3_exp, umeyama

    m = load_flame_dir(tiny_flame["dir"])
    rng = np.random.default_rng(1)
    N, E = 8, 6
    expr = rng.normal(0, 0.5, (N, E))
    expr[:, 0] = 0  # component 0 looks like a jaw rotation; leave it to the jaw pose
    expr[:, 1] = np.linspace(-1.5, 1.5, N)  # a local bump ramps up
    layer = FlameLayer(m, 6, E)
    with torch.no_grad():
        v = layer(torch.zeros(6, dtype=torch.float64), torch.tensor(expr),
                  torch.zeros(N, 5, 3, dtype=torch.float64)).numpy()
    # FLAME frame -> head frame (undo the fixture's transform)
    s, R, t = umeyama(m.v_template, canonical_mesh.vertices)
    v_world = s * v @ R.T + t
    f, W = 500.0, 256
    ang = np.radians(np.linspace(-15, 15, N))
    w2c = np.tile(np.eye(4), (N, 1, 1))
    for i, a in enumerate(ang):
        w2c[i, :3, :3] = so3_exp(torch.tensor([0.0, -a, 0.0])).numpy()
        w2c[i, :3, 3] = [0, 0, -0.5]
    Pc = np.einsum("nab,nvb->nva", w2c[:, :3, :3], v_world) + w2c[:, None, :3, 3]
    uv = np.stack([W / 2 + f * Pc[..., 0] / -Pc[..., 2], W / 2 - f * Pc[..., 1] / -Pc[..., 2]],
                  -1)
    L = np.zeros((N, 478, 3))
    L[:, :468, :2] = uv
    clip = SimpleNamespace(landmarks=L, shots=None)
    sol = SimpleNamespace(w2c=w2c, focal=f, cx=W / 2, cy=W / 2, face_size=100.0,
                          template=canonical_mesh.vertices)
    fit = fit_flame(m, clip, sol, num_expr=E, num_shape=6, iters=300, reg_expr=1e-6,
                    reg_shape=1e-6, smooth=0.0)
    assert fit.expressions.shape == (N, E + 3) and fit.vertices.shape == (N, 468, 3)
    assert fit.names[E:] == ["flame_jaw_rx", "flame_jaw_ry", "flame_jaw_rz"]
    assert np.array_equal(fit.expressions[:, E:], fit.jaw.astype(np.float32))  # β holds the jaw
    assert fit.median_error_px < 0.3
    # the expression channels follow the truth
    assert np.corrcoef(fit.expressions[:, 1], expr[:, 1])[0, 1] > 0.95
    assert np.abs(fit.expressions[:, 1:E] - expr[:, 1:]).mean() < 0.2
    err = np.linalg.norm(fit.vertices - v_world, axis=-1)
    assert np.median(err) < 0.002  # metres
