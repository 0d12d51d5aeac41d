"""The entangled scene: a capture that moves the controls only in fixed groups (and can leave
some out), with the splits that command what it never showed."""

from __future__ import annotations

import numpy as np
import pytest

from flamenerf.data.dataset import load_dataset
from flamenerf.data.dataset_checks import DatasetError
from flamenerf.synthetic.expressions import GROUPS, PAIRS, entangled_trajectory
from flamenerf.synthetic.head import CONTROL_INDEX, CONTROLS
from flamenerf.synthetic.scene import frame_specs, make_scene


def _group_vectors() -> dict[str, np.ndarray]:
    out = {}
    for g, names in GROUPS.items():
        v = np.zeros(len(CONTROLS))
        v[[CONTROL_INDEX[n] for n in names]] = 1.0
        out[g] = v
    return out


def test_the_capture_moves_whole_groups_one_expression_at_a_time():
    e = entangled_trajectory(300, seed=3).astype(np.float64)
    assert e.shape == (300, len(CONTROLS)) and e.min() >= 0 and e.max() <= 1
    assert np.linalg.matrix_rank(e, tol=1e-4) == len(GROUPS)  # never a control alone
    for names in GROUPS.values():  # a group's members always move by the same amount
        if "jawOpen" not in names:
            cols = e[:, [CONTROL_INDEX[n] for n in names]]
            assert np.allclose(cols, cols[:, :1], atol=1e-6), names
    # the expressions never meet: at most one of the groups but the blinks at a time
    own = {g: next(n for n in names if n != "jawOpen") for g, names in GROUPS.items()}
    active = {g: e[:, CONTROL_INDEX[own[g]]] > 1e-3 for g in GROUPS if g != "blink"}
    assert (np.sum(list(active.values()), axis=0) <= 1).all()
    for a, b in PAIRS:
        assert not ((e[:, CONTROL_INDEX[a]] > 1e-3) & (e[:, CONTROL_INDEX[b]] > 1e-3)).any()
    # each group at full strength somewhere
    for g in GROUPS:
        assert e[:, CONTROL_INDEX[own[g]]].max() >= 0.9, g
    assert np.array_equal(e, entangled_trajectory(300, seed=3))


def test_the_scene_leaves_out_the_controls_it_is_told_and_commands_the_pairs(tmp_path):
    out = make_scene(tmp_path / "ent", size=16, frames=12, reanimate=2, leakage_steps=1,
                     workers=1, entangled=True, never=("eyeBlinkLeft", "eyeBlinkRight"))
    ds = load_dataset(out)
    assert ds.source["entangled"] is True
    assert ds.source["never"] == ["eyeBlinkLeft", "eyeBlinkRight"]
    capture = ds.expression_matrix([f for f in ds.frames if f.frame_index is not None])
    assert (capture[:, [CONTROL_INDEX["eyeBlinkLeft"], CONTROL_INDEX["eyeBlinkRight"]]]
            == 0).all()
    leak = ds.split("leakage")  # the sweep still commands the blinks
    assert {f.extra["leakage_control"] for f in leak[1:]} == set(CONTROLS)
    pairs = ds.split("pairs")
    assert [tuple(f.extra["pair"]) for f in pairs] == list(PAIRS)
    for f, x in zip(pairs, ds.expression_matrix(pairs)):
        assert sorted(np.flatnonzero(x)) == sorted(CONTROL_INDEX[n] for n in f.extra["pair"])
        assert np.allclose(f.c2w, leak[0].c2w)


def test_the_default_scene_has_no_pairs_and_names_unknown_controls(tmp_path):
    specs = frame_specs(0, 12, 1.0, reanimate=2, leakage_steps=1)
    assert "pairs" not in {s.split for s in specs}
    with pytest.raises(DatasetError, match="no control named 'eyeBlink'"):
        make_scene(tmp_path / "x", size=16, frames=4, never=("eyeBlink",))
