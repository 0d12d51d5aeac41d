"""Reading datasets: every split of the built-in scene, and one-line errors naming the
file for a corrupted transforms.json."""

from __future__ import annotations

import json

import numpy as np
import pytest

from flamenerf.data.dataset import load_dataset
from flamenerf.data.dataset_checks import DatasetError
from flamenerf.data.playback import frame_rate
from flamenerf.synthetic.head import CONTROLS


def test_load_dataset_reads_every_split(dataset_dir):
    ds = load_dataset(dataset_dir)
    assert set(ds.splits) == {"train", "val", "reanimate", "leakage"}
    assert ds.expression_names == list(CONTROLS) and ds.expression_kind == "synthetic"
    assert all(f.frame_index is not None for f in ds.split("train") + ds.split("val"))
    cap = sorted(ds.split("train") + ds.split("val"), key=lambda f: f.position)
    assert [f.frame_index for f in cap] == list(range(12))
    # `capture`: the clip as filmed, train and val in the order of their codes
    assert [f.frame_index for f in ds.split("capture")] == list(range(12))
    with pytest.raises(DatasetError, match=r"no split named 'nope' \(have: .*reanimate, "
                                           r"train, val, capture\)"):
        ds.split("nope")
    assert frame_rate(ds.split("capture")) is None  # the built-in scene stores no times
    for k, f in enumerate(ds.split("capture")):
        f.extra["time"] = round(k / 15, 6)
    assert frame_rate(ds.split("capture")) == 15.0
    # frames spread unevenly (every 2nd or 3rd of a 30 fps clip) play in the clip's time
    t = np.cumsum([0] + [2 if k % 2 else 3 for k in range(11)]) / 30
    for f, tk in zip(ds.split("capture"), t):
        f.extra["time"] = round(float(tk), 6)
    assert frame_rate(ds.split("capture")) == round(11 / t[-1], 3)
    # a gap (dropped frames) plays for its time at the rate of the steps around it
    from flamenerf.data.playback import playback

    rate, shown = playback(np.array([0.0, 0.1, 0.2, 0.7, 0.8]))
    assert rate == 10.0 and shown.tolist() == [1, 1, 5, 1, 1]
    assert playback(t)[1].tolist() == [1] * len(t)  # unevenly spread, no gap: each once
    assert playback(np.array([0.0, 0.1, 0.2, 0.6]), rate=20.0)[1].tolist() == [1, 1, 8, 1]
    assert playback(np.array([1.0])) is None and playback(np.array([1.0, 1.0])) is None
    assert [f.frame_index for f in ds.split("val")] == [5]
    assert all(f.frame_index is None for f in ds.split("reanimate") + ds.split("leakage"))
    assert len(ds.split("leakage")) == 1 + len(CONTROLS)
    assert ds.face_vertices.shape[0] == len(ds.frames) and 300 <= ds.face_vertices.shape[1] <= 1000
    f = ds.split("reanimate")[0]
    img, m, dep = ds.load_image(f), ds.load_mask(f), ds.load_depth(f)
    assert img.shape == (48, 48, 3) and m.any() and dep is not None
    assert ds.near <= dep.min() and dep.max() <= ds.far
    # the leakage frames share frame 0's camera and body pose
    lk = ds.split("leakage")
    assert all(np.allclose(x.c2w, ds.frames[0].c2w) for x in lk)
    assert all(x.extra["body_pose"] == ds.frames[0].extra["body_pose"] for x in lk)


def test_corrupted_transforms_is_a_dataset_error_naming_the_file(dataset_dir, tmp_path):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(dataset_dir, bad)
    tj = bad / "transforms.json"
    tj.write_text(tj.read_text()[:-200])
    with pytest.raises(DatasetError, match="transforms.json"):
        load_dataset(bad)
    meta = json.loads((dataset_dir / "transforms.json").read_text())
    del meta["frames"][0]["expression"]
    tj.write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="transforms.json"):
        load_dataset(bad)
    meta = json.loads((dataset_dir / "transforms.json").read_text())
    tj.write_text(json.dumps({**meta, "format_version": 99}))
    with pytest.raises(DatasetError, match="transforms.json: format_version 99 is newer"):
        load_dataset(bad)
    tj.write_text(json.dumps({**meta, "format_version": "1"}))
    with pytest.raises(DatasetError, match="format_version '1' is not a version number"):
        load_dataset(bad)
    tj.write_text(json.dumps({**meta, "camera_model": "OPENCV_FISHEYE"}))
    with pytest.raises(DatasetError, match="camera_model 'OPENCV_FISHEYE': flamenerf reads "
                                           "pinhole cameras only"):
        load_dataset(bad)
    tj.write_text(json.dumps({**meta, "prior": "x"}))
    with pytest.raises(DatasetError, match="transforms.json: 'prior' must be an object"):
        load_dataset(bad)


def test_cameras_expressions_and_frame_indices_are_validated(dataset_dir, tmp_path):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(dataset_dir, bad)
    tj = bad / "transforms.json"
    meta = json.loads(tj.read_text())
    for field, value, msg in (
            ("transform_matrix", [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0.5], [0, 0, 0, 1]],
             "transform_matrix must be rigid"),
            ("transform_matrix", np.diag([1.0, 1, -1, 1]).tolist(), "must be rigid"),
            ("expression", [float("nan")] * len(CONTROLS), "not a finite number"),
            ("frame_index", 10 ** 6, "frame_index 1000000 must be below"),
            ("depth_path", 5, "field 'depth_path' has the wrong type"),
            ("file_path", "/etc/passwd", "'/etc/passwd' is outside the dataset"),
            ("mask_path", "../masks/000000.png", "is outside the dataset")):
        m = json.loads(json.dumps(meta))
        m["frames"][1][field] = value
        tj.write_text(json.dumps(m))
        with pytest.raises(DatasetError, match=f"frames\\[1\\]: .*{msg}"):
            load_dataset(bad)


def test_sixteen_bit_images_read_on_the_same_scale(dataset_dir, tmp_path):
    import shutil

    import imageio.v3 as iio

    wide = tmp_path / "wide"
    shutil.copytree(dataset_dir, wide)
    ds = load_dataset(wide)
    f = ds.frames[0]
    grey = iio.imread(wide / f.file_path)[..., 1]  # PNG writers take 16 bits as grey only
    iio.imwrite(wide / f.file_path, grey)
    eight = ds.load_image(f)
    iio.imwrite(wide / f.file_path, grey.astype(np.uint16) * 257)  # the same picture
    sixteen = load_dataset(wide).load_image(f)
    assert np.allclose(sixteen, eight, atol=1e-6) and 0.2 < eight.mean() < 0.9


def test_alpha_is_composited_over_black_and_said_once(dataset_dir, tmp_path, capsys):
    import shutil

    import imageio.v3 as iio

    cut = tmp_path / "cut"
    shutil.copytree(dataset_dir, cut)
    ds = load_dataset(cut)
    f, g = ds.frames[:2]
    rgb = iio.imread(cut / f.file_path)[..., :3]
    alpha = np.zeros(rgb.shape[:2], np.uint8)
    alpha[:, : rgb.shape[1] // 2] = 255  # the left half kept, the right half cut away
    for frame in (f, g):
        iio.imwrite(cut / frame.file_path, np.dstack([rgb, alpha]))
    img = ds.load_image(f)
    assert img.shape == rgb.shape
    assert np.allclose(img[:, : rgb.shape[1] // 2], rgb[:, : rgb.shape[1] // 2] / 255)
    assert img[:, rgb.shape[1] // 2:].max() == 0 and rgb[:, rgb.shape[1] // 2:].max() > 0
    ds.load_image(g)
    err = capsys.readouterr().err
    assert err.count("alpha channel") == 1 and f.file_path in err
    iio.imwrite(cut / f.file_path, np.dstack([rgb[..., 0], alpha]))  # grey with alpha
    grey = ds.load_image(f)
    assert grey.shape == rgb.shape and np.allclose(grey[..., 0], grey[..., 2])
    assert np.allclose(grey[:, 0, 0], rgb[:, 0, 0] / 255)


def test_head_pose_is_optional_validated_and_all_or_none(toy_dataset, tmp_path):
    import shutil

    ds = load_dataset(toy_dataset)
    assert not ds.has_head_poses and all(f.head_pose is None for f in ds.frames)
    posed = tmp_path / "posed"
    shutil.copytree(toy_dataset, posed)
    tj = posed / "transforms.json"
    meta = json.loads(tj.read_text())
    c, s = np.cos(0.3), np.sin(0.3)
    pose = [[c, 0, s, 0.01], [0, 1, 0, -0.02], [-s, 0, c, 0.03], [0, 0, 0, 1]]
    for fr in meta["frames"]:
        fr["head_pose"] = pose
    tj.write_text(json.dumps(meta))
    ds = load_dataset(posed)
    assert ds.has_head_poses and np.allclose(ds.frames[3].head_pose, pose)
    assert "head_pose" not in ds.frames[3].extra
    # a non-rigid matrix, a malformed one, and a dataset where only some frames have one
    for bad, msg in ((np.diag([2.0, 1, 1, 1]).tolist(), "rigid"), ([[1, 2], [3, 4]], "4x4"),
                     ("eye", "4x4"), (None, "frames\\[2\\] lacks a head_pose")):
        m = json.loads(json.dumps(meta))
        if bad is None:
            del m["frames"][2]["head_pose"]
        else:
            m["frames"][2]["head_pose"] = bad
        tj.write_text(json.dumps(m))
        with pytest.raises(DatasetError, match=f"transforms.json.*{msg}"):
            load_dataset(posed)


def test_face_landmarks_are_validated(dataset_dir, tmp_path):
    import shutil

    assert set(load_dataset(dataset_dir).face_landmarks) == {"eye_left", "eye_right", "mouth"}
    copy = tmp_path / "copy"
    shutil.copytree(dataset_dir, copy)
    tj = copy / "transforms.json"
    meta = json.loads(tj.read_text())
    for bad in ({"eye_left": [0], "eye_right": [1]}, {"eye_left": [0], "eye_right": [1],
                                                      "mouth": [10 ** 6]}, [1, 2]):
        meta["face_landmarks"] = bad
        tj.write_text(json.dumps(meta))
        with pytest.raises(DatasetError, match="transforms.json.*face_landmarks"):
            load_dataset(copy)
    del meta["face_landmarks"]  # optional
    tj.write_text(json.dumps(meta))
    assert load_dataset(copy).face_landmarks is None


def test_face_mesh_vertices_must_be_finite_and_in_range(dataset_dir, tmp_path):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(dataset_dir, copy)
    with np.load(copy / "face_mesh.npz") as z:
        faces, verts = z["faces"], z["vertices"].astype(np.float64)
    for bad in (np.nan, 1e308):
        v = verts.copy()
        v[0, 0, 0] = bad
        np.savez(copy / "face_mesh.npz", faces=faces, vertices=v)
        with pytest.raises(DatasetError, match="face_mesh.npz: 'vertices' must be finite"):
            load_dataset(copy)
    np.savez(copy / "face_mesh.npz", faces=np.zeros((0, 3), np.int32), vertices=verts)
    with pytest.raises(DatasetError, match=r"face_mesh.npz: 'faces' must have shape \(F, 3\) "
                                           "with F > 0"):
        load_dataset(copy)
