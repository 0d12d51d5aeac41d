"""The tracker's blendshape stage read from landmarks, and the β -> mesh model fitted to mean
what the tracker means by each control (tracking/blendshapes.py, tracking/expression_model.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from flamenerf.data.dataset import Intrinsics, StoredMeshModel, load_dataset
from flamenerf.data.dataset_checks import DatasetError
from flamenerf.data.dataset_writer import write_mesh_model
from flamenerf.data.mesh_model import fit_dataset_expression_model
from flamenerf.geometry import look_at
from flamenerf.meshes import expression_model_system, fit_expression_model, model_from_coefficients
from flamenerf.tracking.expression_model import Sweep, consistent_coefficients, pinhole_projection


def test_the_blendshape_stage_scores_the_landmarkers_landmarks_as_it_does(landmarker_path):
    from skimage import data

    from flamenerf.tracking import landmarker as lm
    from flamenerf.tracking.blendshapes import BlendshapeStage

    with lm.FaceLandmarker(landmarker_path) as det:
        d = det.detect(data.astronaut())
    stage = BlendshapeStage(landmarker_path)
    assert stage.names == lm.blendshape_names()
    np.testing.assert_allclose(stage.scores(d.landmarks[:, :2]), d.blendshapes, atol=1e-6)
    # the smile's score follows the mouth corners: pulling them apart raises it
    jac = stage.jacobian(d.landmarks[:, :2])
    smile = stage.names.index("mouthSmileLeft")
    assert jac.shape == (52, 478, 2) and np.abs(jac[smile]).max() > 0
    assert not jac[:, 2].any()  # landmark 2 is not read by the network


def _collinear_problem():
    """Two controls that always move together in the training frames, each moving its own
    vertex: control 0 vertex 0 along x, control 1 vertex 1 along y (5 mm at β = 1)."""
    rng = np.random.default_rng(0)
    v = 6
    rest = rng.normal(0, 0.03, (v, 3))
    t = rng.uniform(0, 1, 40)
    beta = np.stack([t, t], 1)
    verts = np.repeat(rest[None], len(t), 0)
    verts[:, 0, 0] += 0.005 * t
    verts[:, 1, 1] += 0.005 * t
    intr = Intrinsics(w=128, h=128, fx=300.0, fy=300.0, cx=64.0, cy=64.0)
    c2w = look_at(np.array([0.0, 0.0, 0.5]), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    project = pinhole_projection(intr, c2w)
    pix0 = project(rest)[0]
    per_px = 300 * 0.005 / 0.5  # pixels of 5 mm at the face

    def score(p):  # a tracker that reads control 0 off vertex 0's x, control 1 off vertex 1's y
        return np.array([(p[0, 0] - pix0[0, 0]) / per_px, -(p[1, 1] - pix0[1, 1]) / per_px])

    def jacobian(p):
        j = np.zeros((2, v, 2))
        j[0, 0, 0] = 1 / per_px
        j[1, 1, 1] = -1 / per_px
        return j

    return rest, beta, verts, project, score, jacobian


def test_collinear_controls_each_get_their_own_motion():
    rest, beta, verts, project, score, jacobian = _collinear_problem()
    x, y = torch.from_numpy(beta), torch.from_numpy(verts)
    neutral, basis = fit_expression_model(x, y)
    # least squares splits the joint motion: control 0 alone reads half of itself and
    # half of control 1
    alone = project(neutral.double().numpy() + basis[0].double().numpy())[0]
    np.testing.assert_allclose(score(alone), [0.5, 0.5], atol=0.05)

    gram, rhs, scale = expression_model_system(x, y)
    sweeps = [Sweep(k, k, np.array([[0.0, 0.0], [0.5, 0.0], [1.0, 0.0]])[:, [k, 1 - k]])
              for k in range(2)]
    coef = consistent_coefficients(gram.numpy(), rhs.numpy(), scale.numpy(), len(beta),
                                   sweeps, score, jacobian, project, strength=10.0)
    neutral2, basis2 = model_from_coefficients(torch.from_numpy(coef), scale)
    for k in range(2):
        got = score(project(neutral2.double().numpy() + basis2[k].double().numpy())[0])
        want = np.eye(2)[k]
        np.testing.assert_allclose(got, want, atol=0.05)
    # the training frames, which cannot tell the two apart, are fitted as well as before
    def fit(n, b):
        return (n[None] + torch.einsum("ne,evc->nvc", x.float(), b) - y).norm(dim=-1)

    assert fit(neutral2, basis2).max() < fit(neutral, basis).max() + 1e-4


def test_a_dataset_keeps_its_mesh_model(toy_dataset, tmp_path):
    import shutil

    root = tmp_path / "ds"
    shutil.copytree(toy_dataset, root)
    ds = load_dataset(root)
    assert ds.mesh_model is None
    n, b = fit_dataset_expression_model(ds)
    write_mesh_model(root, StoredMeshModel(n.numpy() + 1, b.numpy() * 2, 1e-3, "test"))
    ds = load_dataset(root)
    assert ds.mesh_model is not None and ds.mesh_model.method == "test"
    n2, b2 = fit_dataset_expression_model(ds)
    torch.testing.assert_close(n2, n + 1)
    torch.testing.assert_close(b2, b * 2)
    # a run that asks for another ridge, or for the least-squares fit, refits
    torch.testing.assert_close(fit_dataset_expression_model(ds, stored=False)[0], n)
    torch.testing.assert_close(fit_dataset_expression_model(ds, ridge=1e-2)[0],
                               fit_dataset_expression_model(ds, ridge=1e-2, stored=False)[0])
    # a model of the wrong shape is a clear error naming the file
    write_mesh_model(root, StoredMeshModel(n.numpy()[:-1], b.numpy()[:, :-1], 1e-3, "test"))
    with pytest.raises(DatasetError, match="expression_model.npz: expected neutral"):
        load_dataset(root)
