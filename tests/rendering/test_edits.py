"""`render --edit`: controls changed in every frame of a source, the rest as it is; the
clip as filmed (`--split capture`) edited and set beside its frames."""

from __future__ import annotations

import numpy as np
import pytest

from flamenerf.data.companions import Companions
from flamenerf.data.expression_range import ExpressionRange
from flamenerf.errors import UserError
from flamenerf.rendering.edits import apply_edits, describe, file_tag, parse_edits
from flamenerf.rendering.videos import RenderOptions

NAMES = ["jawOpen", "mouthSmileLeft", "mouthUpperUpLeft"]


def test_each_operation_on_every_frame():
    v = np.array([[0.2, 0.1, 0.3], [0.6, 0.4, 0.0]], np.float32)
    for items, want in ((["jawOpen=0.5"], [0.5, 0.5]), (["jawOpen+=0.1"], [0.3, 0.7]),
                        (["jawOpen-=0.1"], [0.1, 0.5]), (["jawOpen*=0"], [0.0, 0.0]),
                        (["jawOpen*=1.5"], [0.3, 0.9])):
        out, moved, _ = apply_edits(v, parse_edits(items, NAMES))
        np.testing.assert_allclose(out[:, 0], want, atol=1e-6)
        np.testing.assert_array_equal(out[:, 1:], v[:, 1:])  # the rest as the source has it
        assert moved == []
    out, *_ = apply_edits(v, parse_edits(["jawOpen=0, mouthSmileLeft+=0.5"], NAMES))
    np.testing.assert_allclose(out, [[0, 0.6, 0.3], [0, 0.9, 0]], atol=1e-6)
    # `all`: every control the other items do not name
    out, *_ = apply_edits(v, parse_edits(["all*=0", "jawOpen*=1"], NAMES))
    np.testing.assert_allclose(out, [[0.2, 0, 0], [0.6, 0, 0]], atol=1e-6)
    out, *_ = apply_edits(v, parse_edits(["all*=2"], NAMES))
    np.testing.assert_allclose(out, 2 * v, atol=1e-6)


def test_companions_follow_each_frames_change():
    """mouthUpperUpLeft rises with the smile in the training frames, so an edit that raises
    the smile by 0.2 raises it by its slope (0.5) times 0.2 in every frame."""
    smile = np.linspace(0, 0.8, 9)
    train = np.stack([np.zeros(9), smile, 0.1 + 0.5 * smile], -1)
    follows = np.zeros((3, 3), bool)
    follows[1, 2] = True
    comp = Companions(NAMES, follows, train)
    v = np.array([[0.0, 0.1, 0.15], [0.3, 0.4, 0.3]], np.float32)
    out, moved, over = apply_edits(v, parse_edits(["mouthSmileLeft+=0.2"], NAMES), comp)
    assert moved == ["mouthUpperUpLeft"] and over == []
    np.testing.assert_allclose(out[:, 1], v[:, 1] + 0.2, atol=1e-6)
    np.testing.assert_allclose(out[:, 2], v[:, 2] + 0.1, atol=1e-3)
    np.testing.assert_array_equal(out[:, 0], v[:, 0])
    # clamped to the training range first (the smile's largest is 0.8), and the companion
    # follows the change that is rendered, not the one asked for
    out, _, over = apply_edits(v, parse_edits(["mouthSmileLeft+=0.6"], NAMES), comp,
                               ExpressionRange.of(NAMES, train))
    np.testing.assert_allclose(out[:, 1], [0.7, 0.8], atol=1e-6)
    np.testing.assert_allclose(out[:, 2], v[:, 2] + 0.5 * (out[:, 1] - v[:, 1]), atol=1e-3)
    # said per control, with the frames it held back
    assert over == ["mouthSmileLeft in 1 of 2 frames (asked up to 1.00; the clip: 0.00-0.80)"]
    _, _, over = apply_edits(v, parse_edits(["mouthSmileLeft-=0.3"], NAMES), comp,
                             ExpressionRange.of(NAMES, train))
    assert over == ["mouthSmileLeft in 1 of 2 frames (asked down to -0.20; the clip: "
                    "0.00-0.80)"]


def test_edits_as_people_type_them():
    """Spaces around the operator (a shell makes three words of them), a pair's stem for
    both sides, a name in another case, `all` without MediaPipe's `_neutral`."""
    names = ["jawOpen", "mouthSmileLeft", "mouthSmileRight", "_neutral"]
    assert [str(e) for e in parse_edits(["mouthSmileLeft", "+=", "0.3"], names)] == [
        "mouthSmileLeft+=0.3"]
    assert [str(e) for e in parse_edits(["mouthSmile+=0.3 jawopen=-0.2"], names)] == [
        "mouthSmileLeft+=0.3", "mouthSmileRight+=0.3", "jawOpen=-0.2"]
    assert [e.name for e in parse_edits(["all*=2"], names)] == names[:3]
    assert describe(["mouthSmile += 0.3,", "all*=0"]) == "mouthSmile+=0.3, all*=0"


@pytest.mark.parametrize("item,message", [
    ("jawOpn=1", "unknown control 'jawOpn'; did you mean 'jawOpen'"),
    ("jawOpen", "expected name=V, name.=D, name-=D or name.=S"),
    ("jawOpen+=much", "'much' is not a number"),
    ("jawOpen=nan", "must be finite"),
    ("jawOpen=1,jawOpen+=1", "jawOpen is edited twice"),
    ("all*=0,all=1", "all is edited twice"),
    (",", "give at least one edit"),
    ("mouthSmileLeft=+0.3", r"to raise it by that write mouthSmileLeft\+=0.3"),
    ("smile+=0.3", "did you mean 'mouthSmileLeft'"),  # the word typed, in a control's name
    ("mouthSmiel+=0.3", "did you mean 'mouthSmileLeft'"),
    ("frown=1", r"unknown control 'frown' \(one of: .*; or all\)"),
])
def test_bad_edits_say_what_is_wrong(item, message):
    with pytest.raises(UserError, match=message):
        parse_edits([item], NAMES)


def test_each_edit_gets_its_own_file_name():
    names = NAMES + ["browInnerUp", "eyeBlinkLeft"]
    assert file_tag(["mouthSmile += .3,", "JAWOPEN*=0"], names) == "mouthSmile+0.3_jawOpenx0"
    assert file_tag(["browInnerUp-=0.2 eyeBlinkLeft=1"], names) == \
        "browInnerUp-0.2_eyeBlinkLeft=1"
    assert file_tag(["all*=1.5"], names) != file_tag(["all*=2"], names)
    assert file_tag([",".join(f"c{i}+=0.1" for i in range(20))], names) == "edited"  # long
    assert file_tag(["a/b+=1"], ["a/b"]) == "edited"  # no folders made of a control's name


@pytest.mark.slow
def test_capture_edited_beside_its_frames(toy_run, tmp_path, monkeypatch):
    """--split capture --edit: the train and val frames in the clip's order, the edited
    control changed (clamped to the training range) and the others as tracked; the prior's
    meshes moved as the expression model moves them for the edit; driving frames beside."""
    from flamenerf.data.video import read_frames
    from flamenerf.rendering import videos
    from flamenerf.training.run import load_run

    ds = load_run(toy_run, "cpu").dataset()
    capture = ds.split("capture")
    assert [f.frame_index for f in capture] == [0, 1, 2, 3, 4, 5]  # train and val, in order
    tracked = ds.expression_matrix(capture)
    jaw = ds.expression_names.index("jawOpen")
    hi = tracked[[f.frame_index < 4 for f in capture], jaw].max()  # the training range's top
    from flamenerf.data import prior

    mesh_function = prior.mesh_function

    def shifting(model, ds):  # a mesh model whose jaw moves the mesh down by 0.1 a unit
        def mesh_of(beta):
            return ds.face_vertices[0] - np.array([0, 0.1, 0], np.float32) * beta[jaw]
        mesh_function(model, ds)
        return mesh_of

    monkeypatch.setattr(prior, "mesh_function", shifting)
    notes = []
    opts = RenderOptions(toy_run, split="capture", edit=["jawOpen+=0.3"], side_by_side=True,
                         device="cpu", companions=False)
    plan = videos.plan_render(opts, log=notes.append)
    summary = videos.render_videos(opts, log=lambda _: None)
    assert summary.paths["rgb"].name == "capture_jawOpen+0.3_split.mp4"
    assert len(read_frames(summary.paths["sbs"])) == 6
    want = np.minimum(tracked[:, jaw] + 0.3, hi)
    np.testing.assert_allclose(plan.values[:, jaw], want, atol=1e-6)
    others = [k for k in range(len(ds.expression_names)) if k != jaw]
    np.testing.assert_array_equal(plan.values[:, others], tracked[:, others])
    assert any("edited jawOpen+=0.3 in every frame" in n for n in notes)
    assert any("clamped" in n and "jawOpen" in n for n in notes)
    assert not any("clamped" in n and "mouthSmileLeft" in n for n in notes)
    shift = (want - tracked[:, jaw])[:, None] * np.array([0, -0.1, 0], np.float32)
    own = ds.face_vertices[[f.position for f in capture]]
    np.testing.assert_allclose(plan.verts, own + shift[:, None], atol=1e-6)


def test_an_edit_typo_fails_before_anything_renders(toy_run, tmp_path):
    from flamenerf.commands.render import render

    with pytest.raises(UserError, match="unknown control 'jawOpn'"):
        render(RenderOptions(toy_run, out=tmp_path / "x.mp4", split="capture",
                             edit=["jawOpn+=1"], device="cpu"))
    assert not (tmp_path / "x.mp4").exists()


def test_an_edit_window_eases_in_and_out():
    from flamenerf.rendering.edits import EditWindow

    w = EditWindow.parse("1:2").weights(30, 10.0)  # 3 s at 10 fps
    assert np.all(w[:10] == 0) and np.all(w[21:] == 0)  # before 1 s and after 2 s
    assert np.all(w[13:18] == 1) and 0 < w[11] < w[12] < 1  # eased over 0.3 s
    assert np.all(np.diff(w[10:14]) > 0)
    np.testing.assert_array_equal(EditWindow.parse("2:").weights(30, 10.0)[:20], 0)
    assert EditWindow.parse(":1").weights(30, 10.0)[0] == 1  # no ease at the video's start
    for text, message in (("2:1", "after the start"), ("x:1", "not a number"),
                          ("1", "START:END"), ("-1:2", "0 or more"),
                          (":", "give a start, an end or both")):
        with pytest.raises(UserError, match=message):
            EditWindow.parse(text)
    with pytest.raises(UserError, match="the video is 3 s long"):
        EditWindow.parse("5:6").weights(30, 10.0)
    with pytest.raises(UserError, match=r"no frame falls inside it .*every 0\.1 s"):
        EditWindow.parse("1:1.05").weights(30, 10.0)  # between two frames


def test_an_edited_sequence_inside_its_window_only():
    from flamenerf.rendering.edits import edit_sequence

    v = np.tile(np.array([[0.2, 0.1, 0.3]], np.float32), (30, 1))
    items = ["jawOpen+=0.4"]
    whole = edit_sequence(v, parse_edits(items, NAMES), items, NAMES, None, None, None, 10.0)
    assert whole.changed.all() and np.allclose(whole.values[:, 0], 0.6)
    assert whole.tag == "jawOpen+0.4" and whole.where == "in every frame"
    part = edit_sequence(v, parse_edits(items, NAMES), items, NAMES, None, None, "1:2", 10.0)
    assert part.tag == "jawOpen+0.4_1-2s" and part.where.startswith("from frame 11 to 19")
    assert np.array_equal(np.flatnonzero(part.changed), np.arange(11, 20))
    assert np.allclose(part.values[~part.changed], v[~part.changed])
    assert np.allclose(part.values[13:18, 0], 0.6) and 0.2 < part.values[11, 0] < 0.6
    assert np.allclose(part.values[:, 1:], v[:, 1:])  # the other controls as they were
    short = edit_sequence(v, parse_edits(items, NAMES), items, NAMES, None, None,
                          "1:1.3", 10.0)
    assert "too short for the whole edit" in short.where


@pytest.mark.slow
def test_a_capture_edited_only_during_a_window(toy_run, tmp_path):
    """The frames outside --edit-during as tracked; inside, the edit (clamped as always);
    the note and the file's name say when."""
    from flamenerf.rendering.videos import plan_render

    notes = []
    opts = RenderOptions(toy_run, split="capture", edit=["jawOpen-=0.05"], edit_during="1:",
                         fps=2.0, device="cpu", companions=False)  # frames at 0, 0.5, ... 2.5 s
    plan = plan_render(opts, log=notes.append)
    tracked = plan.ds.expression_matrix(plan.ds.split("capture"))
    jaw = plan.ds.expression_names.index("jawOpen")
    np.testing.assert_array_equal(plan.values[:3], tracked[:3])  # before 1 s: as tracked
    np.testing.assert_allclose(plan.values[3:, jaw], tracked[3:, jaw] - 0.05, atol=1e-6)
    assert plan.paths["rgb"].name == "capture_jawOpen-0.05_1s-end_split.mp4"
    assert plan.edited.tolist() == [False] * 3 + [True] * 3  # the side by side's titles
    assert any("from frame 3 to 5 (1 s to the end, eased in and out)" in n for n in notes)
    notes.clear()  # a window too short to ease in and out in full says how much shows
    plan_render(RenderOptions(toy_run, split="capture", edit=["jawOpen-=0.05"],
                              edit_during="1:1.6", fps=2.0, device="cpu"), log=notes.append)
    assert any("reaches 25 % of it at most" in n for n in notes), notes  # 0.1 s before 1.6
    with pytest.raises(UserError, match="--edit-during: limits an --edit"):
        RenderOptions(toy_run, split="capture", edit_during="1:2").check()


def test_an_edit_changes_the_source_as_rendered_not_as_asked(toy_run, tmp_path):
    """A source beyond the training range is clamped first, then edited: `jawOpen-=D` on a
    jaw held at the range's top lowers it from there (it was clamped back to the top)."""
    from flamenerf.data.expression_range import training_range
    from flamenerf.rendering.videos import plan_render

    notes = []
    plan = plan_render(RenderOptions(toy_run, expressions=["jawOpen=5"], edit=["jawOpen-=0.01"],
                                     device="cpu", companions=False), log=notes.append)
    jaw = plan.ds.expression_names.index("jawOpen")
    top = training_range(plan.ds).hi[jaw]
    assert plan.values[:, jaw].max() == pytest.approx(top - 0.01, abs=1e-6)
    assert sum("clamped" in n for n in notes) == 1  # the keyframe's; the edit stays inside


def test_a_repeated_edit_flag_keeps_every_edit(toy_run, tmp_path, capsys):
    """`--edit A --edit B` is `--edit A B` (argparse kept only the last occurrence, and the
    first edit was dropped without a word): here the first, mistyped, is seen."""
    from flamenerf import cli

    out = tmp_path / "x.mp4"
    rc = cli.main(["render", str(toy_run), "--split", "capture", "--edit", "jawOpn+=1",
                   "--edit", "jawOpen+=0.1", "--out", str(out), "--device", "cpu"])
    assert rc == 2 and "unknown control 'jawOpn'" in capsys.readouterr().err
    assert not out.exists()
    assert cli.merge_repeated(["R", "--edit=a", "--size", "8", "--edit", "b", "c", "-h"],
                              {"--edit"}) == ["R", "--edit", "a", "b", "c", "--size", "8", "-h"]
    # tyro's underscore spelling is the same flag; after `--` nothing is an option
    assert cli.merge_repeated(["R", "--head_pose", "a", "--head-pose", "b"], {"--head-pose"}) \
        == ["R", "--head-pose", "a", "b"]
    assert cli.merge_repeated(["R", "--edit", "a", "--", "--edit", "b"], {"--edit"}) \
        == ["R", "--edit", "a", "--", "--edit", "b"]
    flags = cli.list_flags(cli.available_commands()["render"])
    assert {"--edit", "--expressions", "--head-pose"} <= flags and "--size" not in flags
    assert not cli.list_flags(cli.available_commands()["view"])  # --track appends itself
