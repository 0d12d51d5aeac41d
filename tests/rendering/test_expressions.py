"""Expression sources: keyframes, files, mapping by control name, and their errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from flamenerf.errors import UserError
from flamenerf.rendering import expressions as X

NAMES = ["jawOpen", "mouthSmileLeft", "browInnerUp"]
BASE = np.array([0.1, 0.2, 0.3], np.float32)


def test_keyframes_override_named_controls_only():
    v = X.parse_keyframe("jawOpen=0.8, browInnerUp=1", NAMES, BASE)
    np.testing.assert_allclose(v, [0.8, 0.2, 1.0])


def test_keyframes_take_a_pairs_stem_and_any_case_as_edits_do():
    """`mouthSmile=0.3` sets both sides (as `--edit mouthSmile+=0.3` does), `JAWOPEN` the
    jaw; a message quotes the keyframe as typed."""
    names = NAMES + ["mouthSmileRight"]
    base = np.append(BASE, 0.25).astype(np.float32)
    v = X.parse_keyframe("mouthSmile=0.7, JAWOPEN=0.5", names, base)
    np.testing.assert_allclose(v, [0.5, 0.7, 0.3, 0.7])
    with pytest.raises(UserError, match=r"--expressions 'mouthSmile=x': 'x' is not a number"):
        X.parse_keyframe("mouthSmile=x", names, base)
    with pytest.raises(UserError, match="mouthSmileLeft is given twice"):
        X.parse_keyframe("mouthSmile=0.1,mouthSmileLeft=0.2", names, base)


def test_keyframes_move_companions_and_say_so():
    """With a dataset's companions a keyframe also moves the controls the tracker reads
    with the named one (here mouthSmileLeft with the jaw); without them it does not."""
    from flamenerf.data.companions import fit_companions

    rng = np.random.default_rng(0)
    jaw = rng.uniform(0, 1, 50)
    train = np.stack([jaw, 0.5 * jaw, rng.uniform(0, 1, 50)], 1)
    comp = fit_companions(NAMES, "arkit", 468, train)
    seq = X.from_items(["jawOpen=0.6"], NAMES, BASE, 9, comp)
    np.testing.assert_allclose(seq.values[4], [0.6, 0.2 + 0.5 * 0.5, 0.3], atol=0.02)
    assert any("mouthSmileLeft" in n for n in seq.notes)
    # a pair's stem and another case, with companions (their note names what moved)
    assert X.from_items(["JAWOPEN=0.6"], NAMES, BASE, 9, comp).notes == seq.notes
    plain = X.from_items(["jawOpen=0.9"], NAMES, BASE, 9)
    np.testing.assert_allclose(plain.values[4], [0.9, 0.2, 0.3])
    assert not plain.notes


def test_unknown_control_names_the_problem():
    with pytest.raises(UserError, match="unknown control 'jawOpn'; did you mean 'jawOpen'"):
        X.from_items(["jawOpn=1"], NAMES, BASE, 10)
    with pytest.raises(UserError, match="'lots' is not a number"):
        X.from_items(["jawOpen=lots"], NAMES, BASE, 10)
    with pytest.raises(UserError, match="expected name=value"):
        X.from_items(["smile"], NAMES, BASE, 10)


def test_keyframe_sequence_eases_from_and_back_to_the_base():
    seq = X.from_items(["jawOpen=1"], NAMES, BASE, 9)
    assert len(seq) == 9 and seq.resizable
    np.testing.assert_allclose(seq.values[0], BASE)
    np.testing.assert_allclose(seq.values[-1], BASE)
    np.testing.assert_allclose(seq.values[4], [1.0, 0.2, 0.3])
    assert np.all(np.diff(seq.values[:5, 0]) >= 0)
    two = X.keyframe_sequence(np.stack([np.ones(3), np.zeros(3)]), BASE, 7)
    np.testing.assert_allclose(two[2], 1.0)
    np.testing.assert_allclose(two[4], 0.0)


def test_tour_moves_each_control_the_clip_shows_alone_to_the_end_of_its_range():
    """`--expressions tour`: each control the training frames show, in turn, from the base
    to its 99th percentile (or 1st, where farther from the base) and back (a Left/Right
    pair together); controls that do not move are left out, and so is one frame's glitch;
    24 frames a keyframe (and one) unless a length is given, each keyframe on a frame."""
    names = ["jawOpen", "eyeBlinkLeft", "eyeBlinkRight", "cheekPuff", "browInnerUp"]
    base = np.zeros(5, np.float32)
    rng = np.random.default_rng(0)
    smile_now_and_then = np.where(np.arange(200) % 40 == 0, 0.6, 0.0)  # 5 frames of 200
    train = np.stack([rng.uniform(0, 0.8, 200), smile_now_and_then,
                      rng.uniform(0, 1, 200), np.full(200, 0.02),  # cheekPuff: still
                      rng.uniform(0, 0.5, 200)], 1)
    train[7, 3] = 0.9  # a glitch of the tracker in one frame
    seq = X.from_items(["tour"], names, base, None, training=train)
    assert seq.label == "tour" and seq.resizable and len(seq) == 3 * X.TOUR_FRAMES + 1
    assert "jawOpen, eyeBlink, browInnerUp" in seq.notes[0]
    v = seq.values
    np.testing.assert_allclose(v[0], base, atol=1e-6)
    np.testing.assert_allclose(v[-1], base, atol=1e-6)
    assert v[:, 3].max() == 0  # the still control never moves
    top = np.percentile(train, 99, axis=0)
    assert top[1] == 0.6  # in 2.5 % of the frames: the 95th percentile would be 0
    for cols in ([0], [1, 2], [4]):  # each keyframe's peak: its controls alone at the top
        k = int(np.argmax(v[:, cols[0]]))
        np.testing.assert_allclose(v[k, cols], top[cols], atol=1e-5)
        others = [j for j in range(5) if j not in cols]
        assert np.abs(v[k, others]).max() < 1e-3, (cols, v[k])
    assert len(X.from_items(["tour"], names, base, 50, training=train)) == 50
    # sideways moves and gaze go one side at a time: not one motion on two sides
    side = ["jawLeft", "jawRight", "eyeLookInLeft", "eyeLookInRight"]
    seq = X.from_items(["tour"], side, np.zeros(4, np.float32), None,
                       training=rng.uniform(0, 1, (100, 4)))
    assert "jawLeft, jawRight, eyeLookInLeft, eyeLookInRight" in seq.notes[0]
    # signed controls (FLAME's) go to the end of their range farther from the base; a side
    # that does not move itself keeps the base, and the side that does is named as it is
    flame = np.stack([rng.normal(0, 1, 300), rng.uniform(-2, -0.4, 300),
                      rng.uniform(0, 1, 300), np.full(300, 0.3)], 1)
    names4 = ["exp0", "exp1", "mouthSmileLeft", "mouthSmileRight"]
    base4 = np.array([2.0, -0.45, 0.0, 0.3], np.float32)
    keys, shown = X.tour_keyframes(flame, names4, base4)
    lo, hi = np.percentile(flame, [1, 99], axis=0)
    assert shown == ["exp0", "exp1", "mouthSmileLeft"] and len(keys) == 5
    assert keys[0][0] == pytest.approx(lo[0], abs=1e-5)  # base 2.0: the far end is below
    assert keys[2][1] == pytest.approx(lo[1], abs=1e-5)  # always negative: down to -2
    assert keys[4][2] == pytest.approx(hi[2], abs=1e-5) and keys[4][3] == pytest.approx(0.3)
    # scores go up while the base leaves room: a pair both ways (frame 0's left brow near
    # its top would otherwise go down while the right one goes up); with no room, down
    brows = np.stack([rng.uniform(0, 0.8, 300), rng.uniform(0, 0.6, 300)], 1)
    pair = ["browOuterUpLeft", "browOuterUpRight"]
    keys, _ = X.tour_keyframes(brows, pair, np.array([0.75, 0.3], np.float32))
    np.testing.assert_allclose(keys[0], np.percentile(brows, 99, axis=0), atol=1e-5)
    keys, _ = X.tour_keyframes(brows, pair, np.array([0.8, 0.55], np.float32))
    np.testing.assert_allclose(keys[0], np.percentile(brows, 1, axis=0), atol=1e-5)
    # too few frames for the peaks: said
    short = X.from_items(["tour"], names4, base4, 4, training=flame)
    assert len(short) == 4 and "too few" in short.notes[1]
    with pytest.raises(UserError, match="`tour` goes alone"):
        X.from_items(["tour", "jawOpen=1"], names, base, None, training=train)
    with pytest.raises(UserError, match="no control moves"):
        X.from_items(["tour"], names, base, None, training=np.zeros((10, 5)))


def test_track_json_is_mapped_by_name(tmp_path):
    p = tmp_path / "drive.json"
    p.write_text(json.dumps({"names": ["_neutral", "browInnerUp", "jawOpen"], "fps": 25,
                             "frames": [[0.5, 0.1, 0.9], [0.5, 0.2, 0.8]]}))
    seq = X.load_file(p, NAMES)
    np.testing.assert_allclose(seq.values, [[0.9, 0, 0.1], [0.8, 0, 0.2]])  # missing = 0
    assert seq.fps == 25 and "_neutral" in seq.notes[0]
    p.write_text(json.dumps({"names": ["eyeBlinkLeft"], "frames": [[1.0]]}))
    with pytest.raises(UserError, match="none of its controls"):
        X.load_file(p, NAMES)


def test_vector_and_named_files(tmp_path):
    np.save(tmp_path / "e.npy", np.arange(12, dtype=np.float32).reshape(4, 3))
    assert X.load_file(tmp_path / "e.npy", NAMES).values.shape == (4, 3)
    np.save(tmp_path / "w.npy", np.zeros((4, 5)))
    with pytest.raises(UserError, match="w.npy: has 5 values per frame, this run has 3"):
        X.load_file(tmp_path / "w.npy", NAMES)
    (tmp_path / "h.csv").write_text("jawOpen,cheekPuff\n0.5,1\n0.25,0\n")
    seq = X.load_file(tmp_path / "h.csv", NAMES)
    np.testing.assert_allclose(seq.values, [[0.5, 0, 0], [0.25, 0, 0]])
    assert "cheekPuff" in seq.notes[0]
    (tmp_path / "n.csv").write_text("1,2,3\n4,5,6\n")
    assert X.load_file(tmp_path / "n.csv", NAMES).values.tolist() == [[1, 2, 3], [4, 5, 6]]
    (tmp_path / "d.json").write_text(json.dumps([{"jawOpen": 1}, {"browInnerUp": 0.5}]))
    np.testing.assert_allclose(X.load_file(tmp_path / "d.json", NAMES).values,
                               [[1, 0, 0], [0, 0, 0.5]])
    (tmp_path / "u.json").write_text(json.dumps({"jawOpen": 1, "smirk": 1}))
    with pytest.raises(UserError, match="u.json: unknown control 'smirk'"):
        X.load_file(tmp_path / "u.json", NAMES)
    with pytest.raises(UserError, match="nothere.json: expression file does not exist"):
        X.from_items([str(tmp_path / "nothere.json")], NAMES, BASE, 5)
    for empty in ({}, [{}, {}]):  # every control silently 0: refused
        (tmp_path / "e.json").write_text(json.dumps(empty))
        with pytest.raises(UserError, match="e.json: names no controls"):
            X.load_file(tmp_path / "e.json", NAMES)
    (tmp_path / "f.json").write_text(json.dumps([{}, {"jawOpen": 1}]))  # a neutral frame
    np.testing.assert_allclose(X.load_file(tmp_path / "f.json", NAMES).values,
                               [[0, 0, 0], [1, 0, 0]])
    # what once rendered a flat grey video, or a traceback
    for name, text, message in (
            ("nan.csv", "jawOpen\nnan\n", "nan.csv: contains non-finite values"),
            ("twice.csv", "jawOpen,jawOpen\n1,0\n", "twice.csv: jawOpen is named twice"),
            ("big.csv", "jawOpen\n1e30\n", "big.csv: a value of 1e\\+30"),
            ("bin.csv", b"\xff\xfe\x00j\x00a", "bin.csv: not a text CSV file")):
        f = tmp_path / name
        f.write_bytes(text if isinstance(text, bytes) else text.encode())
        with pytest.raises(UserError, match=message):
            X.load_file(f, NAMES)
    (tmp_path / "t.json").write_text('{"names": ["jawOpen"], "frames": [[1]], "fps": NaN}')
    with pytest.raises(UserError, match="t.json: 'fps': the frame rate must be a number"):
        X.load_file(tmp_path / "t.json", NAMES)


def test_the_side_by_sides_bars_show_what_moves_first():
    """With many controls the panel shows those that differ from the first frame before
    the largest still ones: a tour's small control is not hidden."""
    from flamenerf.images import expression_panel, panel_rows

    base = np.zeros(52)
    base[:10] = 0.3  # ten still controls, larger than the moving one
    v = base.copy()
    v[40], v[41] = 0.12, 0.005  # one moves, one only by a hair
    rows, moved = panel_rows(v, 8, base)
    assert 40 in rows and 41 not in rows and len(rows) == 8 and moved.sum() == 1
    assert rows == sorted(rows)  # in the model's order
    assert panel_rows(v, 8)[0] == list(range(8))  # without a reference: the largest
    img = expression_panel(v, [f"c{j}" for j in range(52)], 64, 64, ref=base)
    assert img.shape == (64, 64, 3) and 0 <= img.min() and img.max() <= 1


def test_a_split_outside_the_capture_plays_at_the_stills_rate(toy_dataset):
    """The built-in scene's re-animation frames are each a new expression from a new
    camera: at a clip's rate its 10 frames flashed by; the capture keeps the clip's."""
    from flamenerf.data.dataset import load_dataset

    ds = load_dataset(toy_dataset)
    assert X.from_split(ds, "reanimate").fps == X.STILLS_FPS == 4
    assert X.from_split(ds, "capture").fps == ds.frame_rate()
