"""`flamenerf preprocess` end to end on short videos made from a real face photo, and its
error paths (one clear line, non-zero exit, nothing half-written)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from flamenerf.cli import main
from flamenerf.data.dataset import load_dataset
from flamenerf.errors import UserError
from flamenerf.tracking.pipeline import PreprocessOptions, preprocess_video


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, gappy_video, landmarker_path):
    out = tmp_path_factory.mktemp("pre") / "ds"
    rc = main(["preprocess", str(gappy_video), str(out), "--size", "128", "--val-every", "4",
               "--dilate", "2", "--consistent-expressions"])
    assert rc == 0
    return out


@pytest.mark.slow
def test_dataset_is_valid_and_complete(dataset):
    ds = load_dataset(dataset)
    assert (ds.intrinsics.w, ds.intrinsics.h) == (128, 128)
    assert ds.expression_kind == "arkit" and ds.expression_dim == 52
    assert "jawOpen" in ds.expression_names
    n = len(ds.frames)
    assert n == 10  # 12 frames, 2 without a face
    assert [f.frame_index for f in ds.frames] == list(range(n))
    assert ds.splits["val"] == [3, 7] and len(ds.splits["train"]) == 8
    assert [f.extra["source_frame"] for f in ds.frames] == [0, 1, 2, 4, 5, 6, 8, 9, 10, 11]
    assert 0 < ds.near < ds.far
    # MediaPipe's 468 mesh vertices and its ten iris points, each iris in its eye
    assert ds.faces.shape == (898, 3) and ds.face_vertices.shape == (n, 478, 3)
    v = ds.face_vertices.astype(np.float64)
    for iris, corners in ((468, (33, 133)), (473, (263, 362))):
        centre = v[:, list(corners)].mean(1)
        eye_width = np.linalg.norm(v[:, corners[0]] - v[:, corners[1]], axis=-1)
        assert np.all(np.linalg.norm(v[:, iris] - centre, axis=-1) < 0.6 * eye_width)
    expr = ds.expression_matrix(ds.frames)
    assert np.all((expr >= 0) & (expr <= 1))
    # the β -> mesh model fitted to the tracker's reading is kept with the dataset
    assert ds.mesh_model is not None and ds.mesh_model.method.startswith("tracker-consistent")
    assert ds.mesh_model.basis.shape == (52, 478, 3)


@pytest.mark.slow
def test_masks_cover_the_projected_face(dataset):
    from flamenerf.geometry import project_points

    ds = load_dataset(dataset)
    for f in ds.frames[::3]:
        m = ds.load_mask(f)
        assert 0.05 < m.mean() < 0.6
        uv, z = project_points(ds.face_vertices[f.position].astype(np.float64),
                               ds.intrinsics, f.c2w)
        assert np.all(z > ds.near) and np.all(z < ds.far)
        ij = np.clip(np.round(uv - 0.5).astype(int), 0, 127)
        assert m[ij[:, 1], ij[:, 0]].mean() > 0.98
        # the face pixels are the astronaut's skin: brighter red than green/blue
        rgb = ds.load_image(f)[m]
        assert rgb[:, 0].mean() > rgb[:, 2].mean()


@pytest.mark.slow
def test_report_lists_dropped_frames_and_qa_files(dataset):
    qa = dataset / "qa"
    for name in ("overlay.mp4", "cameras.png", "contact_sheet.png", "tracking_report.json"):
        assert (qa / name).is_file(), name
    rep = json.loads((qa / "tracking_report.json").read_text())
    assert rep["selected_frames"] == 12 and rep["tracked_frames"] == 10
    assert [d["source_frame"] for d in rep["dropped"]] == [3, 7]
    assert all(d["reason"] == "no face detected" for d in rep["dropped"])
    assert rep["reprojection_error_px"]["rigid_median_out"] < 2.0
    assert len(rep["frames"]) == 10
    # what the training frames cover: each control's range (what renders clamp to)
    cov = rep["expressions"]
    assert sorted(cov["varying"] + cov["barely_moving"]) == sorted(cov["controls"])
    ds = load_dataset(dataset)
    train = ds.expression_matrix(ds.split("train"))
    for k, name in enumerate(ds.expression_names):
        c = cov["controls"][name]
        assert c["min"] == pytest.approx(train[:, k].min(), abs=1e-6)
        assert c["max"] == pytest.approx(train[:, k].max(), abs=1e-6)
        assert (name in cov["varying"]) == (c["p95"] - c["p5"] >= 0.1)


def test_overwrite_and_no_half_written_output(tmp_path, astronaut_video, capsys):
    out = tmp_path / "ds"
    out.mkdir()
    assert main(["preprocess", str(astronaut_video), str(out)]) == 2
    assert "already exists" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == [out]


def _fails(video, out, capsys, *extra):
    rc = main(["preprocess", str(video), str(out), *extra])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("flamenerf: error: ")
    assert not out.exists()
    assert [p for p in out.parent.iterdir() if p.name.startswith(".")] == []  # no temp dirs
    return err[0]


def test_video_without_a_face(tmp_path, noface_video, capsys):
    msg = _fails(noface_video, tmp_path / "ds", capsys)
    assert str(noface_video) in msg and "no face found in any of the 6" in msg


def test_too_few_frames_tracked(tmp_path, mostly_noface_video, capsys):
    msg = _fails(mostly_noface_video, tmp_path / "ds", capsys)
    assert "only 2 of 10" in msg and str(mostly_noface_video) in msg


def test_a_one_frame_video_says_so(tmp_path, capsys):
    """One frame, with a face: what is short is the frames, not the tracking."""
    from media import astronaut_frames, write_mp4

    one = write_mp4(tmp_path / "one.mp4", astronaut_frames(1))
    msg = _fails(one, tmp_path / "ds", capsys)
    assert "only 1 frame selected from the video's 1" in msg and "--fps" in msg


def test_unreadable_video(tmp_path, capsys):
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"\x00\x00\x00\x18ftypmp42" + b"\x00" * 100)
    msg = _fails(bad, tmp_path / "ds", capsys)
    assert "broken.mp4" in msg
    msg = _fails(tmp_path / "missing.mp4", tmp_path / "ds", capsys)
    assert "missing.mp4: file does not exist" in msg


def test_wrong_model_path(tmp_path, astronaut_video, capsys):
    msg = _fails(astronaut_video, tmp_path / "ds", capsys, "--landmarker",
                 str(tmp_path / "nowhere" / "face_landmarker.task"))
    assert "nowhere/face_landmarker.task: landmarker model file does not exist" in msg


@pytest.mark.slow
def test_failure_after_writing_started_leaves_nothing(tmp_path, astronaut_video,
                                                      monkeypatch):
    import flamenerf.tracking.qa as qa

    def boom(*a, **k):
        raise RuntimeError("disk full")

    monkeypatch.setattr(qa, "plot_cameras", boom)
    with pytest.raises(RuntimeError):
        preprocess_video(astronaut_video, tmp_path / "ds",
                         PreprocessOptions(size=64, progress=False))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_flame_backend_end_to_end(tmp_path, astronaut_video, tiny_flame):
    out = tmp_path / "ds"
    rep = preprocess_video(astronaut_video, out, PreprocessOptions(
        size=64, face_model="flame", flame_dir=tiny_flame["dir"], flame_expr_dim=4,
        qa=False, progress=False))
    ds = load_dataset(out)
    assert ds.expression_kind == "flame" and ds.expression_dim == 4 + 3  # + the jaw pose
    assert ds.expression_names[-3:] == ["flame_jaw_rx", "flame_jaw_ry", "flame_jaw_rz"]
    assert ds.face_vertices.shape == (12, 468, 3)
    assert ds.meta["expression_model"]["fit_error_px"] < 5.0
    assert rep["kept_frames"] == 12
    assert ds.load_mask(ds.frames[0]).mean() > 0.05


def test_flame_needs_its_files(tmp_path, astronaut_video):
    with pytest.raises(UserError, match="--flame-dir"):
        preprocess_video(astronaut_video, tmp_path / "ds",
                         PreprocessOptions(face_model="flame", progress=False))
    with pytest.raises(UserError, match="FLAME directory does not exist"):
        preprocess_video(astronaut_video, tmp_path / "ds", PreprocessOptions(
            face_model="flame", flame_dir=tmp_path / "FLAME", progress=False))


@pytest.mark.slow
def test_a_clip_too_short_for_a_val_split_says_so(tmp_path, astronaut_video, capsys):
    """12 frames held out one in 20: a dataset without val, and a note saying why and what
    to change (eval needs held-out frames)."""
    out = tmp_path / "ds"
    assert main(["preprocess", str(astronaut_video), str(out), "--size", "64",
                 "--val-every", "20", "--cameras", "head"]) == 0
    assert "val" not in json.loads((out / "qa" / "tracking_report.json").read_text())["splits"]
    note = [line for line in capsys.readouterr().out.splitlines() if line.startswith("note:")]
    assert note and "no val split" in note[0] and "--val-every 20" in note[0]


@pytest.mark.slow
def test_other_faces_are_named_and_native_logs_stay_out(tmp_path, two_faces_video, capfd):
    """preprocess on a clip with two faces: one line says so; and COLMAP's bundle
    adjustment (its binding sets its own log level) prints none of its log lines."""
    out = tmp_path / "ds"
    assert main(["preprocess", str(two_faces_video), str(out), "--size", "32", "--no-qa"]) == 0
    got = capfd.readouterr()
    assert "other faces were in view in 8 of the selected frames" in got.out
    rep = json.loads((out / "qa" / "tracking_report.json").read_text())
    assert rep["crowded_frames"] == list(range(8)) and rep["cuts"] == []
    assert rep["scene"]["background"]["status"] == "registered"  # so the adjustment ran
    assert "bundle_adjustment" not in got.err + got.out
