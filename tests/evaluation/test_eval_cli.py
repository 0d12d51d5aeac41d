"""`flamenerf eval` and `flamenerf compare` end to end on a toy run."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import pytest

from flamenerf.commands.compare import compare
from flamenerf.commands.eval import eval as eval_cmd
from flamenerf.errors import UserError


def _strict(path):
    def no_constants(name):
        raise ValueError(f"non-standard JSON constant {name}")

    return json.loads(path.read_text(), parse_constant=no_constants)


@pytest.fixture(scope="module")
def evaluated(toy_run, tmp_path_factory):
    out = tmp_path_factory.mktemp("eval") / "eval"
    eval_cmd(toy_run, fit_steps=3, fit_batch_rays=64, out=out, device="cpu", images=1)
    return out


@pytest.mark.slow
def test_eval_writes_the_documented_schema(evaluated):
    res = _strict(evaluated / "metrics.json")
    assert res["format"] == "flamenerf-eval" and res["version"] == 1
    assert res["method"] == "FLAME-in-NeRF" and res["expression_mode"] == "masked"
    assert res["view_directions"] == "captured"  # as `render` and the viewer show it
    assert "- view directions: captured" in (evaluated / "metrics.md").read_text()
    assert res["resolution"] == [16, 16]
    assert res["protocol"]["fit_steps"] == 3 and res["protocol"]["split"] == "val"
    h = res["heldout"]
    for k in ("mse", "psnr", "ssim", "psnr_face", "psnr_face_interior", "psnr_background",
              "psnr_scene", "fit_seconds"):
        assert isinstance(h[k], float), k
    assert isinstance(res["driven"]["psnr_scene"], float)
    # the rendered face's depth against the quad's (0.5 .. 1.6 is the toy's depth range)
    assert 0.0 <= res["driven"]["face_depth_error"] < 1.1
    assert "face depth error (mm)" in (evaluated / "metrics.md").read_text()
    assert h["num_frames"] == len(h["frames"]) == 2
    assert h["psnr"] == pytest.approx(np.mean([f["psnr"] for f in h["frames"]]))
    assert {f["frame_index"] for f in h["frames"]} == {4, 5}
    assert res["reanimate"]["num_frames"] == 2
    lk = res["leakage"]
    assert lk["num_frames"] == 3 and len(lk["frames"]) == 2
    assert lk["mean"] == 0.0  # the spatial prior
    assert res["separation"] is None  # the toy's quad has no eyes or mouth: no face parts
    assert (evaluated / "metrics.md").read_text().startswith("# Evaluation")
    for rel in res["images"]:
        img = iio.imread(evaluated / rel)
        assert img.ndim == 3 and img.shape[0] >= 128
    assert sorted(res["images"]) == ["images/driven_00.png", "images/leakage.png",
                                     "images/reanimate_00.png", "images/val_00.png"]
    d = res["driven"]  # nothing fitted: the val frames with frame 0's codes
    assert d["num_frames"] == len(d["frames"]) == 2 and d["split"] == "val"
    assert d["psnr_face"] == pytest.approx(np.mean([f["psnr_face"] for f in d["frames"]]))
    assert h["budget"]["updates_per_frame"] == 3
    rt = d["retracked"]  # the driven renders re-tracked, beside the frames themselves
    assert rt["frames"] == 2 and rt["responding"] == 0 and rt["truth"]["responding"] == 0
    # the toy quad is no face: every control read, none detected
    assert rt["controls"] and all(c["detected"] == 0 for c in rt["controls"].values())
    ct = res["control"]  # the toy's quad is no face: re-tracking finds none, and says so
    assert ct["source"].startswith("the dataset's leakage sweep")
    assert ct["controls"]["jawOpen"]["detected"] == 0 and ct["mean_gain"] is None
    assert "**Control response**" in (evaluated / "metrics.md").read_text()


def test_eval_can_render_at_the_directions_asked(toy_run, tmp_path):
    eval_cmd(toy_run, fit_steps=1, fit_batch_rays=32, out=tmp_path / "eval", device="cpu",
             images=0, control=False, captured_directions=False)
    assert _strict(tmp_path / "eval" / "metrics.json")["view_directions"] == "as asked"


@pytest.mark.slow
def test_eval_drive_reports_the_driving_correlation(toy_run, astronaut_video, tmp_path):
    out = tmp_path / "eval"
    eval_cmd(toy_run, fit_steps=1, fit_batch_rays=32, out=out, device="cpu", images=0,
             control=False, drive=astronaut_video, drive_frames=4)
    res = _strict(out / "metrics.json")
    dv = res["drive"]
    assert dv["frames"] == 4 and dv["video"] == str(astronaut_video)
    # a still photo drives nothing enough to measure, and the report says so
    assert dv["controls"] == {} and dv["skipped"]
    assert dv["geometry"]["measures"] == {} and "mouth_open" in dv["geometry"]["skipped"]
    assert "images/drive.png" in res["images"]
    img = iio.imread(out / "images" / "drive.png")
    h = (img.shape[0] - 2) // 2  # driving over render, 2 px apart
    assert h > 8
    # the driving frames are cut to a square around the face, each as wide as its render
    assert img.shape[1] == 4 * h + 3 * 4
    assert "**Drive**" in (out / "metrics.md").read_text()
    with pytest.raises(UserError, match="missing.mp4: file does not exist"):
        eval_cmd(toy_run, out=tmp_path / "e2", drive=tmp_path / "missing.mp4")
    assert not (tmp_path / "e2").exists()


@pytest.mark.slow
def test_compare_prints_a_table(evaluated, tmp_path, capsys):
    out = tmp_path / "table.md"
    compare([evaluated / "metrics.json", evaluated / "metrics.json"], labels=["A", "B"],
            out=out)
    text = capsys.readouterr().out
    lines = [ln for ln in text.splitlines() if ln.startswith("|")]
    assert lines[0].startswith("| Method | Preset | Steps | MSE ↓ | PSNR ↑ |")
    assert len(lines) == 4 and lines[2].startswith("| A |") and lines[3].startswith("| B |")
    assert "Leakage ↓" in lines[0]
    assert out.read_text() == text.split("wrote")[0]
    compare([evaluated / "metrics.json"], latex=True)
    assert r"\toprule" in capsys.readouterr().out
    # as every command: an existing output is replaced only when asked
    with pytest.raises(UserError, match="table.md: already exists.*--overwrite"):
        compare([evaluated / "metrics.json"], out=out)
    assert out.read_text() == text.split("wrote")[0]
    compare([evaluated / "metrics.json"], labels=["C"], out=out, overwrite=True)
    assert "| C |" in out.read_text()


def test_compare_names_a_missing_eval(tmp_path):
    with pytest.raises(UserError, match="metrics.json: file is missing.*flamenerf eval"):
        compare([tmp_path])


@pytest.mark.slow
def test_compare_refuses_a_newer_metrics_format(evaluated, tmp_path):
    import json

    d = json.loads((evaluated / "metrics.json").read_text())
    for version, words in ((99, "version 99 is newer"), ("1", "version '1' is not a version")):
        d["version"] = version
        (tmp_path / "metrics.json").write_text(json.dumps(d))
        with pytest.raises(UserError, match=f"metrics.json: {words}"):
            compare([tmp_path / "metrics.json"])


def test_eval_of_a_missing_run_names_it(tmp_path):
    with pytest.raises(UserError, match="nope: run directory does not exist"):
        eval_cmd(tmp_path / "nope")


def test_the_drive_report_counts_the_controls_at_the_bar():
    from flamenerf.evaluation.report import eval_markdown

    res = {"resolution": [8, 8], "drive": {
        "video": "v.mp4", "frames": 3, "mean_correlation": 0.7, "mean_gain": 0.85,
        "controls": {"jawOpen": {"correlation": 0.95, "gain": 0.8},
                     "eyeBlinkLeft": {"correlation": 0.5, "gain": 0.9}},
        "responding": 1, "ground_truth": {"controls": {}, "responding": 2, "mean_gain": 1.0,
                                          "mean_correlation": 1.0}}}
    text = eval_markdown(res)
    assert "correlation ≥ 0.9: **1** of 2 (ground truth 2)." in text
    del res["drive"]["ground_truth"]
    assert "correlation ≥ 0.9: **1** of 2." in eval_markdown(res)


def test_the_table_counts_controls_following_only_where_the_frames_show_them():
    from flamenerf.evaluation.report import compare_markdown

    def res(n: int, truth: int) -> dict:
        return {"heldout": {"psnr": 30.0},
                "driven": {"retracked": {"responding": n, "truth": {"responding": truth}}}}

    head, _, a, b = compare_markdown([res(24, 27), res(2, 27)], ["fast", "nerfies"]).split("\n")[:4]
    assert head.endswith("| Controls following ↑ |")
    assert a.endswith("| **24** |") and b.endswith("| 2 |")
    # the built-in head: the tracker reads none of its val expressions, frames included
    assert "Controls following" not in compare_markdown([res(0, 0), res(0, 0)])


def test_the_table_gives_the_truths_control_gain_beside_the_runs():
    """A model's re-tracked gain means something only beside the ground truth's own (the
    tracker reads a small scene weakly): a column, never marked best."""
    from flamenerf.evaluation.report import compare_markdown

    def res(gain: float) -> dict:
        return {"heldout": {"psnr": 30.0}, "control": {"mean_gain": gain, "mean_gt_gain": 0.37}}

    head, _, a, b = compare_markdown([res(-0.09), res(0.2)]).split("\n")[:4]
    assert head.endswith("| Control gain ↑ | Control gain, truth |")
    assert a.endswith("| -0.09 | 0.37 |") and b.endswith("| **0.20** | 0.37 |")
