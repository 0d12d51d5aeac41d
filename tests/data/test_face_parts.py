"""Face parts of named controls, and the β -> mesh fit limited to them: co-varying tracker
scores must not let a brow control move the jaw."""

import numpy as np
import torch

from flamenerf.data.face_parts import applies, control_weights
from flamenerf.meshes import expression_mesh, fit_expression_model

NAMES = ["_neutral", "browInnerUp", "eyeBlinkLeft", "eyeBlinkRight", "jawOpen",
         "mouthSmileLeft", "jawLeft", "someOtherControl"]


def _face(n: int = 468, seed: int = 0) -> np.ndarray:
    """A flat face-shaped cloud in MediaPipe's numbering where it matters: the eye corners
    at y = 2.7 (the subject's left at +x), the mouth at y = -4.2 (units: cm)."""
    rng = np.random.default_rng(seed)
    v = np.stack([rng.uniform(-7, 7, n), rng.uniform(-9, 8, n), np.zeros(n)], 1)
    v[263], v[362] = (4.5, 2.7, 0), (1.5, 2.7, 0)
    v[33], v[133] = (-4.5, 2.7, 0), (-1.5, 2.7, 0)
    v[13], v[14], v[61], v[291] = (0, -4.0, 0), (0, -4.4, 0), (-2.5, -4.2, 0), (2.5, -4.2, 0)
    return v


def test_parts_follow_the_names_and_the_sides():
    v = _face()
    w = control_weights("arkit", NAMES, v)
    assert w.shape == (468, len(NAMES))
    col = {n: w[:, i] for i, n in enumerate(NAMES)}
    chin = np.linalg.norm(v - (0, -8, 0), axis=1) < 1.0
    brow = np.linalg.norm(v - (-3, 5.5, 0), axis=1) < 0.8
    left_eye = np.linalg.norm(v - (3, 2.7, 0), axis=1) < 1.0
    right_eye = np.linalg.norm(v - (-3, 2.7, 0), axis=1) < 1.0
    assert chin.any() and brow.any() and left_eye.any() and right_eye.any()
    assert (col["jawOpen"][chin] == 1).all() and (col["jawOpen"][brow] == 0).all()
    assert (col["browInnerUp"][brow] == 1).all() and (col["browInnerUp"][chin] == 0).all()
    assert (col["eyeBlinkLeft"][left_eye] == 1).all()
    assert (col["eyeBlinkLeft"][right_eye] == 0).all()
    assert (col["eyeBlinkRight"][right_eye] == 1).all()
    # the brows are the brow controls' alone, though they lie within an eye's radius
    above = np.linalg.norm(v - (3, 4.9, 0), axis=1) < 0.4  # 0.32 eye-mouth units over the eye
    assert above.any() and (col["eyeBlinkLeft"][above] == 0).all()
    assert (col["browInnerUp"][above] == 1).all()
    # ... and the eyes not the brow controls', though the upper face reaches down to them:
    # a brow control that moved the lids learnt a clip's wide eyes, and an edit of the brows
    # over a squint repainted the eyes
    lid = (np.linalg.norm(v - (3, 2.7, 0), axis=1) < 0.6) & (v[:, 1] < 3.0)
    assert lid.any() and (col["browInnerUp"][lid] == 0).all()
    assert (col["eyeBlinkLeft"][lid] == 1).all()
    assert (col["_neutral"] == 0).all()
    assert (col["someOtherControl"] == 1).all()  # unknown names are not limited
    # jawLeft moves the whole jaw sideways: not cut at the midline
    assert (col["jawLeft"][chin] == 1).all()
    # other kinds and topologies get no limits
    assert control_weights("flame", NAMES, v) is None
    assert control_weights("arkit", NAMES, v[:400]) is None


def test_the_limited_fit_keeps_a_correlated_brow_control_off_the_jaw():
    v = torch.from_numpy(_face()).float()
    names = ["browInnerUp", "jawOpen"]
    w = torch.from_numpy(control_weights("arkit", names, v.numpy()))
    lower = (v[:, 1] < -6).float()[:, None] * torch.tensor([0.0, -1.0, 0.0])  # jaw drops
    upper = (v[:, 1] > 5).float()[:, None] * torch.tensor([0.0, 0.5, 0.0])   # brows rise
    g = torch.Generator().manual_seed(1)
    jaw = torch.rand(120, generator=g)
    brow = (jaw + 0.1 * torch.randn(120, generator=g)).clamp(0, 1)  # a surprised face
    betas = torch.stack([brow, jaw], 1)
    meshes = (v + brow[:, None, None] * upper + jaw[:, None, None] * lower
              + 0.05 * torch.randn(120, *v.shape, generator=g))  # tracking noise
    neutral, basis = fit_expression_model(betas, meshes, weights=w)
    jaw_v, brow_v = v[:, 1] < -6, v[:, 1] > 5
    assert basis[0][jaw_v].abs().max() == 0  # the brow control cannot move the jaw
    assert basis[1][brow_v].abs().max() == 0
    assert torch.allclose(basis[1][jaw_v], lower[jaw_v], atol=0.1)
    assert torch.allclose(basis[0][brow_v], upper[brow_v], atol=0.1)
    # commanding jawOpen alone opens the jaw fully
    opened = expression_mesh(neutral, basis, torch.tensor([0.0, 1.0]))
    drop = (opened - expression_mesh(neutral, basis, torch.zeros(2)))[jaw_v, 1]
    assert (drop < -0.9).all()


def test_all_ones_weights_are_the_free_fit():
    g = torch.Generator().manual_seed(2)
    betas, meshes = torch.rand(30, 3, generator=g), torch.randn(30, 20, 3, generator=g)
    free = fit_expression_model(betas, meshes)
    ones = fit_expression_model(betas, meshes, weights=torch.ones(20, 3))
    for a, b in zip(free, ones):
        assert torch.allclose(a, b, atol=1e-5)


def test_the_prior_radius_follows_whether_the_parts_apply(dataset_dir):
    from flamenerf.config import RADIUS_FREE, RADIUS_PARTS, preset
    from flamenerf.data.dataset import load_dataset
    from flamenerf.data.face_parts import applies
    from flamenerf.training.trainer import build_for_dataset

    assert applies("arkit", NAMES, 468) and applies("arkit", NAMES, 478)
    assert not applies("synthetic", NAMES, 468) and not applies("arkit", ["a", "b"], 468)
    cfg = preset("fast")
    assert cfg.model.expression_regions.radius is None
    assert cfg.model.expression_regions.resolved_radius(True) == RADIUS_PARTS
    ds = load_dataset(dataset_dir)
    m = build_for_dataset(cfg, ds)  # the built-in scene: face parts, not a tracked clip
    # β enters `fast` centred on the training frames' mean; the paper's preset takes it as is
    train = ds.expression_matrix(ds.split("train"))
    assert torch.allclose(m.expression.mean, torch.from_numpy(train.mean(0)))
    assert m.expression.mean.abs().amax() > 0.01
    assert float(build_for_dataset(preset("flame-in-nerf"), ds).expression.mean.abs().amax()) == 0
    assert cfg.model.expression_regions.radius == RADIUS_FREE == m.cfg.expression_regions.radius
    # the mesh guide: on wherever the face parts are known (tracked clips, the built-in
    # scene), off where they are not (here: the built-in scene without its landmarks)
    assert preset("fast").model.mesh_guide.enabled is None
    assert preset("fast").model.mesh_guide.resolved_enabled(True) is True
    assert cfg.model.mesh_guide.enabled is True and m.expression.mesh_guided
    ds.face_landmarks = None
    bare = build_for_dataset(preset("fast"), ds)
    assert not bare.expression.mesh_guided and bare.cfg.expression_regions.radius == RADIUS_FREE
    off = preset("fast")
    off.model.mesh_guide.enabled = False
    assert off.model.mesh_guide.resolved_enabled(True) is False
    assert preset("flame-in-nerf").model.mesh_guide.resolved_enabled(True) is False


def test_the_builtin_scene_names_its_eyes_and_mouth_and_gets_face_parts(dataset_dir):
    """The built-in mesh's lips slide into the open mouth (not linear in jawOpen): without
    face parts a fit may hand that to a blink. With them a blink cannot reach the mouth and
    the jaw cannot reach the eyes, while the parts' defaults for tracked clips stay off."""
    from flamenerf.data.dataset import load_dataset
    from flamenerf.data.head_pose import canonical_vertices
    from flamenerf.data.mesh_model import fit_dataset_expression_model

    ds = load_dataset(dataset_dir)
    assert ds.face_landmarks is not None
    assert not applies(ds.expression_kind, ds.expression_names, ds.face_vertices.shape[1])
    _, basis = fit_dataset_expression_model(ds)
    v = canonical_vertices(ds, ds.training_frames()).mean(0)
    mouth = v[ds.face_landmarks["mouth"]].mean(0)
    eye = v[ds.face_landmarks["eye_left"]].mean(0)
    span = np.linalg.norm(eye - mouth)
    near_mouth = torch.from_numpy(np.linalg.norm(v - mouth, axis=1) < 0.3 * span)
    near_eye = torch.from_numpy(np.linalg.norm(v - eye, axis=1) < 0.2 * span)
    k = {n: i for i, n in enumerate(ds.expression_names)}
    motion = basis.norm(dim=-1)  # (E, V)
    assert motion[k["jawOpen"]][near_mouth].amax() > 1e-3  # the jaw opens (metres)
    for name in ("eyeBlinkLeft", "eyeBlinkRight", "eyeWideLeft", "browInnerUp"):
        assert motion[k[name]][near_mouth].amax() == 0, name
    assert motion[k["jawOpen"]][near_eye].amax() == 0


def test_train_notes_a_builtin_scene_without_landmarks(dataset_dir, tmp_path, capsys):
    import json
    import shutil

    from flamenerf.commands.train import note_missing_landmarks

    note_missing_landmarks(dataset_dir)
    assert "landmarks" not in capsys.readouterr().out
    old = tmp_path / "old"
    shutil.copytree(dataset_dir, old)
    meta = json.loads((old / "transforms.json").read_text())
    del meta["face_landmarks"]
    (old / "transforms.json").write_text(json.dumps(meta))
    note_missing_landmarks(old)
    assert "names no face landmarks" in capsys.readouterr().out
