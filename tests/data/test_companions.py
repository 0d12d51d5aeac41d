"""Companions: the controls a tracker reads together, moved with the named ones."""

import numpy as np
import pytest

from flamenerf.data.companions import fit_companions

NAMES = ["eyeBlinkLeft", "eyeLookDownLeft", "eyeBlinkRight", "eyeLookDownRight", "jawOpen",
         "mouthLowerDownLeft", "mouthLowerDownRight", "browInnerUp", "_neutral"]


def clip_expressions(n=200, seed=0):
    """Scores as MediaPipe gives them on a real face: a closed eye also reads as looking
    down (0.8 of the blink), an open mouth as lowerDown on both sides, and the surprised
    frames raise the brows with the jaw (which companions must not carry over)."""
    rng = np.random.default_rng(seed)
    e = np.zeros((n, len(NAMES)))
    blink_l, blink_r, jaw = rng.uniform(0, 1, (3, n))
    e[:, 0], e[:, 2], e[:, 4] = blink_l, blink_r, 0.6 * jaw
    e[:, 1] = 0.8 * blink_l + 0.02 * rng.standard_normal(n) + 0.1
    e[:, 3] = 0.8 * blink_r + 0.02 * rng.standard_normal(n) + 0.1
    e[:, 5] = e[:, 6] = 0.5 * jaw
    e[:, 7] = 0.9 * jaw  # co-varies with the jaw, but is another part of the face
    e[:, 8] = rng.uniform(0, 1, n)
    return e


def test_a_blink_brings_its_own_eyes_look_down_and_nothing_else():
    e = clip_expressions()
    comp = fit_companions(NAMES, "arkit", 478, e)
    assert comp.of("eyeBlinkLeft") == ["eyeLookDownLeft"]  # not the right eye, not the brows
    base = e[0].copy()
    out = comp.complete(base, {0: 1.0})
    assert out[0] == 1.0
    assert out[1] - base[1] == pytest.approx(0.8 * (1.0 - base[0]), abs=0.03)
    untouched = [2, 3, 4, 5, 6, 7, 8]
    assert np.array_equal(out[untouched], base[untouched])


def test_the_jaw_brings_both_sides_of_the_lower_face_but_not_the_brows():
    e = clip_expressions()
    comp = fit_companions(NAMES, "arkit", 468, e)
    assert set(comp.of("jawOpen")) == {"mouthLowerDownLeft", "mouthLowerDownRight"}
    base = e[0].copy()
    out = comp.complete(base, {4: base[4] + 0.2})
    assert out[5] - base[5] == pytest.approx(0.2 * 0.5 / 0.6, abs=0.01)
    assert out[7] == base[7]


def test_companions_stay_in_the_training_range_and_named_controls_win():
    e = clip_expressions()
    comp = fit_companions(NAMES, "arkit", 478, e)
    base = e[0].copy()
    out = comp.complete(base, {0: 5.0})  # far past anything the frames show
    assert out[1] == pytest.approx(e[:, 1].max())
    both = comp.complete(base, {0: 1.0, 1: 0.0})  # a closed eye told to look straight
    assert both[1] == 0.0


def test_no_companions_without_face_parts():
    e = clip_expressions()
    assert fit_companions(NAMES, "flame", 478, e) is None  # FLAME components
    assert fit_companions(NAMES, "arkit", 5023, e) is None  # not MediaPipe's mesh
    assert fit_companions(["expr_0", "expr_1"], "arkit", 468, e[:, :2]) is None
