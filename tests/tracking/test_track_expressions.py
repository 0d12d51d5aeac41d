"""`flamenerf track`: the expression JSON, relative transfer, and its errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from flamenerf.cli import main
from flamenerf.errors import UserError
from flamenerf.tracking.expressions import (ExpressionTrack, estimate_neutral,
                                            load_expressions, save_expressions,
                                            transfer_relative)


def test_track_writes_the_documented_format(tmp_path, gappy_video, landmarker_path):
    out = tmp_path / "drive.json"
    assert main(["track", str(gappy_video), "--out", str(out), "--fps", "5"]) == 0
    d = json.loads(out.read_text())
    assert d["format"] == "flamenerf-expressions" and d["kind"] == "arkit"
    assert len(d["names"]) == 52 and d["fps"] == pytest.approx(5.0)
    # every other frame of 12 at 10 fps: 0 2 4 6 8 10, none of them the grey frames 3, 7
    assert d["source_frames"] == [0, 2, 4, 6, 8, 10]
    assert len(d["frames"]) == 6 and all(len(r) == 52 for r in d["frames"])
    assert d["times"][1] == pytest.approx(0.2)
    tr = load_expressions(out)
    assert tr.frames.shape == (6, 52) and tr.kind == "arkit"
    smile = [d["names"].index("mouthSmileLeft"), d["names"].index("mouthSmileRight")]
    assert tr.frames[:, smile].mean() > 0.3  # the astronaut smiles


def test_a_driver_among_other_faces_is_followed(tmp_path, two_faces_video, landmarker_path,
                                                capsys):
    out = tmp_path / "drive.json"
    assert main(["track", str(two_faces_video), "--out", str(out)]) == 0
    assert "other faces were in view in 8 of the selected frames" in capsys.readouterr().out
    d = json.loads(out.read_text())
    assert d["source"]["crowded_frames"] == list(range(8)) and len(d["frames"]) == 8


def test_dropped_frames_are_listed(tmp_path, gappy_video, landmarker_path):
    out = tmp_path / "drive.json"
    assert main(["track", str(gappy_video), "--out", str(out)]) == 0
    d = json.loads(out.read_text())
    assert [x["source_frame"] for x in d["dropped"]] == [3, 7]
    assert len(d["frames"]) == 10


def test_relative_transfer_math():
    drive = np.array([[0.1, 0.5], [0.3, 0.9], [0.1, 0.1]])
    out = transfer_relative(drive, np.array([0.1, 0.1]), np.array([0.2, 0.0]), "arkit")
    np.testing.assert_allclose(out, [[0.2, 0.4], [0.4, 0.8], [0.2, 0.0]], atol=1e-6)
    out = transfer_relative(drive, np.array([0.5, 0.5]), np.zeros(2), "flame")
    assert out.min() < 0  # FLAME coefficients are not clipped
    n, used = estimate_neutral(np.array([[1.0, 1], [0.1, 0], [0.9, 0.9], [0, 0.2]]), k=2)
    assert used == [1, 3]
    np.testing.assert_allclose(n, [0.05, 0.1])


@pytest.mark.slow
def test_relative_to_a_dataset(tmp_path, gappy_video, landmarker_path):
    ds = tmp_path / "subject"
    assert main(["preprocess", str(gappy_video), str(ds), "--size", "32", "--no-qa"]) == 0
    out = tmp_path / "drive.json"
    assert main(["track", str(gappy_video), "--out", str(out), "--relative-to", str(ds),
                 "--driver-neutral-frame", "0"]) == 0
    tr = load_expressions(out)
    assert tr.transfer["mode"] == "relative" and tr.transfer["driver_neutral_frames"] == [0]
    # frame 0 is the driver's neutral, so it maps onto the subject's neutral
    np.testing.assert_allclose(tr.frames[0], tr.transfer["subject_neutral"], atol=1e-5)
    assert np.all((tr.frames >= 0) & (tr.frames <= 1))


def test_track_errors(tmp_path, noface_video, astronaut_video, capsys):
    out = tmp_path / "drive.json"
    assert main(["track", str(noface_video), "--out", str(out)]) == 2
    assert "no face found" in capsys.readouterr().err
    assert not out.exists()
    assert main(["track", str(astronaut_video), "--out", str(out), "--relative-to",
                 str(tmp_path / "nodata")]) == 2
    assert "nodata" in capsys.readouterr().err
    assert main(["track", str(astronaut_video), "--out", str(out),
                 "--driver-neutral-frame", "99", "--relative-to", str(tmp_path)]) == 2
    capsys.readouterr()
    assert list(tmp_path.iterdir()) == []
    # folders made for an output never written go again
    assert main(["track", str(noface_video), "--out", str(tmp_path / "a" / "b" / "d.json")]) == 2
    capsys.readouterr()
    assert list(tmp_path.iterdir()) == []


def test_load_expressions_validates(tmp_path):
    p = tmp_path / "e.json"
    save_expressions(p, ExpressionTrack(["a", "b"], np.array([[0.1, 0.2]], np.float32)))
    assert load_expressions(p).names == ["a", "b"]
    p.write_text(json.dumps({"names": ["a", "b"], "frames": [[0.1]]}))
    with pytest.raises(UserError, match="e.json"):
        load_expressions(p)
    p.write_text("{")
    with pytest.raises(UserError, match="not valid JSON"):
        load_expressions(p)


@pytest.mark.slow
def test_track_with_flame(tmp_path, astronaut_video, tiny_flame):
    out = tmp_path / "drive.json"
    assert main(["track", str(astronaut_video), "--out", str(out), "--face-model", "flame",
                 "--flame-dir", str(tiny_flame["dir"]), "--flame-expr-dim", "3"]) == 0
    tr = load_expressions(out)
    assert tr.kind == "flame" and tr.frames.shape == (12, 6)  # 3 coefficients + jaw pose
    assert tr.names == ["flame_expr_000", "flame_expr_001", "flame_expr_002",
                        "flame_jaw_rx", "flame_jaw_ry", "flame_jaw_rz"]
