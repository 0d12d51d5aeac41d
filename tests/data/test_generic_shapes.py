"""Generic shapes for eye and brow controls a clip never moves: a blink shuts the lid of its
own eye and moves nothing else; only controls left still get one."""

from __future__ import annotations

import numpy as np
import pytest

from flamenerf.data.dataset import load_dataset
from flamenerf.data.face_parts import control_weights, face_frame, mesh_landmarks
from flamenerf.data.generic_shapes import COVER, SHAPES, generic_basis, uncovered
from flamenerf.data.mesh_model import fit_dataset_expression_model, generic_controls
from flamenerf.synthetic.scene import make_scene


@pytest.fixture(scope="module")
def no_blink(tmp_path_factory):
    return load_dataset(make_scene(tmp_path_factory.mktemp("noblink") / "scene", size=24,
                                   frames=8, reanimate=0, leakage_steps=0, workers=1,
                                   never=("eyeBlinkLeft", "eyeBlinkRight")))


def test_a_generic_blink_shuts_its_own_eye_and_nothing_else(no_blink):
    ds = no_blink
    names = ds.expression_names
    v = ds.face_vertices[0]
    g = generic_basis(ds.expression_kind, names, v, ds.face_landmarks)
    assert g.shape == (len(names), len(v), 3)
    f = face_frame(v, mesh_landmarks(len(v), ds.face_landmarks))
    weights = control_weights(ds.expression_kind, names, v, ds.face_landmarks)
    for k, name in enumerate(names):
        moved = np.linalg.norm(g[k], axis=1) > 0
        if name not in SHAPES:
            assert not moved.any(), name
            continue
        assert moved.any(), name
        # within the control's own part of the face (its side included)
        assert (weights[moved, k] > 0).all(), name
        along = g[k] @ f.up
        if name.startswith("eyeBlink"):
            assert (along[moved] < 0).all() and -along.min() > 0.05 * f.scale  # down, far
        elif name.startswith(("eyeWide", "browInnerUp")):
            assert (along[moved] > 0).all()
        else:
            assert (along[moved] < 0).all()


def test_only_the_controls_left_still_take_a_generic_shape(no_blink):
    names = no_blink.expression_names
    blinks = sorted(names.index(n) for n in ("eyeBlinkLeft", "eyeBlinkRight"))
    top = no_blink.expression_matrix(no_blink.training_frames()).max(0)
    still = [k for k, n in enumerate(names) if n in SHAPES and top[k] < COVER]
    assert set(blinks) <= set(still) and generic_controls(no_blink) == still
    e = np.zeros((5, len(names)))
    e[:, names.index("browInnerUp")] = COVER * 1.5
    e[:, names.index("jawOpen")] = 0.0  # no generic shape for the jaw
    assert names.index("browInnerUp") not in uncovered(names, e)
    assert names.index("jawOpen") not in uncovered(names, e)
    _, fitted = fit_dataset_expression_model(no_blink, stored=False)
    _, filled = fit_dataset_expression_model(no_blink, stored=False, generic=True)
    g = generic_basis(no_blink.expression_kind, names, fit_dataset_expression_model(
        no_blink, stored=False)[0].numpy(), no_blink.face_landmarks)
    for k in range(len(names)):
        want = g[k] if k in still else fitted[k].numpy()
        np.testing.assert_allclose(filled[k].numpy(), want, atol=1e-7)


def test_a_run_acts_on_a_generic_control_through_the_mesh_alone(no_blink):
    import torch

    from flamenerf.config import preset
    from flamenerf.data.expression_range import training_range
    from flamenerf.training.trainer import build_for_dataset, settle_dataset_defaults

    names = no_blink.expression_names
    blinks = [names.index("eyeBlinkLeft"), names.index("eyeBlinkRight")]
    cfg = preset("fast")
    settle_dataset_defaults(cfg, no_blink)
    model = build_for_dataset(cfg, no_blink)
    assert set(blinks) <= set(model.generic_controls)
    assert model.init_args["generic_controls"] == model.generic_controls
    regions = model.expression.mesh_regions
    assert torch.all(regions[:, blinks] == 0)  # the fields never see them ...
    assert torch.all(model.expression.mesh_basis[blinks].norm(dim=-1).amax(-1) > 0)  # ... the mesh does
    rng = training_range(no_blink, model.generic_controls)
    assert (rng.hi[blinks] == 1.0).all() and rng.hi[names.index("jawOpen")] < 1.0 + 1e-9
    cfg.model.mesh_guide.generic_shapes = False
    plain = build_for_dataset(cfg, no_blink)
    assert plain.generic_controls == [] and "generic_controls" not in plain.init_args
