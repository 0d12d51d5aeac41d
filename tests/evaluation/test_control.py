"""Control metrics: the regression, the sweep range, re-tracking on images whose answer is
known, and the driven/control sections of `evaluate_run`."""

import math

import numpy as np
import pytest

from flamenerf.evaluation import control as C


def test_fit_line_recovers_slope_and_correlation():
    x = np.linspace(0, 1, 6)
    g, r = C.fit_line(x, 0.4 * x + 0.1)
    assert g == pytest.approx(0.4) and r == pytest.approx(1.0)
    g, r = C.fit_line(x, np.full(6, 0.2))  # a control that does nothing
    assert abs(g) < 1e-12 and math.isnan(r)
    g, r = C.fit_line(np.ones(4), x[:4])
    assert math.isnan(g)


def test_sweep_values_cover_the_training_range():
    vals = np.concatenate([np.zeros(50), np.linspace(0, 0.8, 50)])
    s = C.sweep_values(vals, 5)
    assert len(s) == 5 and s[0] == pytest.approx(np.percentile(vals, 5))
    assert s[-1] == pytest.approx(np.percentile(vals, 95))
    assert C.sweep_values(np.full(20, 0.3), 5) is None


def test_control_response_tells_a_working_control_from_a_dead_one():
    names = ["jawOpen", "eyeBlinkLeft", "notAControl"]
    train = np.random.default_rng(0).uniform(0, 1, (40, 3))

    def render(beta):  # an "image" that carries the commanded values
        return beta

    def track(img):  # jawOpen seen at half strength, eyeBlinkLeft ignored
        return {"jawOpen": 0.5 * img[0], "eyeBlinkLeft": 0.3}

    res = C.control_response(render, names, np.zeros(3), train, track, steps=4)
    assert set(res["controls"]) == {"jawOpen", "eyeBlinkLeft"}  # notAControl: not trackable
    assert res["controls"]["jawOpen"]["gain"] == pytest.approx(0.5)
    assert res["controls"]["jawOpen"]["correlation"] == pytest.approx(1.0)
    assert abs(res["controls"]["eyeBlinkLeft"]["gain"]) < 1e-9
    assert res["responding"] == 1  # the jaw at gain 0.5 meets the bar; the blink does not


def test_responds_is_the_issue_bar():
    assert C.responds(0.5, 0.9) and C.responds(1.2, 0.99)
    assert not C.responds(0.49, 1.0) and not C.responds(1.0, 0.89)
    assert not C.responds(math.nan, 1.0) and not C.responds(1.0, math.nan)


def test_control_response_with_companions_sweeps_what_a_keyframe_renders():
    """A model that learned the closed eye only with the eye looking down: the blink swept
    alone does nothing, swept with its companion (as a keyframe renders it) it closes."""
    from flamenerf.data.companions import fit_companions

    names = ["eyeBlinkLeft", "eyeLookDownLeft", "jawOpen"]
    rng = np.random.default_rng(0)
    blink = rng.uniform(0, 1, 60)
    train = np.stack([blink, 0.9 * blink, rng.uniform(0, 0.5, 60)], 1)
    comp = fit_companions(names, "arkit", 468, train)

    def track(img):  # the eye shows closed as far as both controls agree
        return {"eyeBlinkLeft": min(img[0], img[1] / 0.9), "jawOpen": img[2]}

    renders = []

    def render(beta):
        renders.append(beta)
        return beta

    res = C.control_response(render, names, np.zeros(3), train, track, steps=4,
                             companions=comp)
    blink_row, jaw = res["controls"]["eyeBlinkLeft"], res["controls"]["jawOpen"]
    assert abs(blink_row["gain"]) < 1e-9
    assert blink_row["gain_with_companions"] == pytest.approx(1.0, abs=0.05)
    assert blink_row["companions"] == ["eyeLookDownLeft"]
    assert "gain_with_companions" not in jaw  # no companion in this model
    assert len(renders) == 4 * 2 + 4 * 2 + 4  # the two eye controls twice, the jaw once
    assert res["mean_gain_with_companions"] > res["mean_gain"]
    assert res["responding"] == 1 and res["responding_with_companions"] == 2  # + the blink


def test_landmark_gain_reads_how_far_the_face_moves_along_the_mesh_model():
    rng = np.random.default_rng(0)
    rest = rng.uniform(0, 100, (468, 2))
    direction = np.zeros((468, 2))
    direction[:20, 1] = -3.0  # the brows go up by 3 px at the last step ...
    direction[20:25, 1] = -0.5  # ... a few neighbours a little (below the cut: not counted)
    steps = np.linspace(0, 1, 5)
    expected = [rest + t * direction for t in steps]
    half = [rest + 0.5 * t * direction + 5.0 for t in steps]  # half the motion; shifted
    gain, corr, px = C.landmark_gain(half, expected)
    assert gain == pytest.approx(0.5) and corr == pytest.approx(1.0) and px == pytest.approx(3.0)
    # vertices the command barely moves do not count (there the tracker's noise is larger
    # than the command's motion)
    noisy = [h.copy() for h in half]
    for t, h in zip(steps, noisy):
        h[20:25] += 30 * t * direction[20:25]
    assert C.landmark_gain(noisy, expected)[0] == pytest.approx(0.5)
    # motion elsewhere on the face does not count as the command's
    wrong = [rest + t * np.roll(direction, 100, 0) for t in steps]
    assert abs(C.landmark_gain(wrong, expected)[0]) < 1e-9
    # a step without a face is left out; the first one without a face leaves nothing to read
    assert C.landmark_gain([half[0], None, *half[2:]], expected)[0] == pytest.approx(0.5)
    assert math.isnan(C.landmark_gain([None, *half[1:]], expected)[0])
    # a command the mesh model does not move
    assert math.isnan(C.landmark_gain(half, [rest] * 5)[0])


def test_control_response_reads_sweeps_as_geometry_where_given():
    """A control whose score the tracker misses but whose geometry moves as the mesh model
    says: score gain 0, landmark gain 1."""
    names = ["browInnerUp", "jawOpen"]
    train = np.random.default_rng(0).uniform(0, 1, (40, 2))
    rest = np.zeros((468, 2))

    def mesh(beta):  # brows up by 4 px per unit, the jaw down by 10
        m = rest.copy()
        m[:10, 1] -= 4 * beta[0]
        m[10:20, 1] += 10 * beta[1]
        return m

    def render(beta):
        return beta

    def track(img):  # the scores see the jaw only
        return {"browInnerUp": 0.0, "jawOpen": float(img[1])}

    motion = C.LandmarkMotion(expected=mesh, read=lambda img: (track(img), mesh(img)))
    res = C.control_response(render, names, np.zeros(2), train, track, steps=4, motion=motion)
    brow = res["controls"]["browInnerUp"]
    assert abs(brow["gain"]) < 1e-9
    assert brow["landmark_gain"] == pytest.approx(1.0)
    assert brow["landmark_correlation"] == pytest.approx(1.0)
    assert res["mean_landmark_gain"] == pytest.approx(1.0)
    assert "landmark_gain" not in C.control_response(render, names, np.zeros(2), train, track,
                                                     steps=4)["controls"]["jawOpen"]
    # the mesh's own scores: a mesh model whose brow motion the tracker reads at half gain
    motion.mesh_scores = lambda beta: {"browInnerUp": 0.5 * beta[0], "jawOpen": beta[1]}
    res = C.control_response(render, names, np.zeros(2), train, track, steps=4, motion=motion)
    assert res["controls"]["browInnerUp"]["mesh_gain"] == pytest.approx(0.5)
    assert res["controls"]["jawOpen"]["mesh_gain"] == pytest.approx(1.0)
    assert res["mean_mesh_gain"] == pytest.approx(0.75)


def _face(mouth: float, eye_l: float, eye_r: float, scale: float = 1.0) -> np.ndarray:
    """478 landmarks with the eye centres 2·scale apart and the given gaps (in units of
    that distance)."""
    p = np.zeros((478, 3))
    p[[263, 362], 0], p[[33, 133], 0] = scale, -scale  # eye centres at x = ±scale
    d = 2 * scale
    p[13, 1], p[14, 1] = 0, mouth * d
    p[386, 1], p[374, 1] = 0, eye_l * d
    p[159, 1], p[145, 1] = 0, eye_r * d
    return p


def test_openings_are_gaps_over_the_eye_distance_at_any_scale():
    for scale in (1.0, 37.0):
        o = C.openings(_face(0.3, 0.1, 0.05, scale))
        assert o["mouth_open"] == pytest.approx(0.3)
        assert o["eye_open_left"] == pytest.approx(0.1)
        assert o["eye_open_right"] == pytest.approx(0.05)


def test_part_change_says_which_part_an_edit_repainted():
    """A brow edit that repaints the eyes shows as change inside the eyes' outlines."""
    outlines = C.part_outlines()
    assert {len(v) for v in outlines.values()} == {1, 2}  # lips one outline; eyes, brows two
    marks = np.zeros((478, 2))
    centres = {"eyes": [(40, 30), (20, 30)], "brows": [(40, 18), (20, 18)], "lips": [(30, 50)]}
    for part, sides in outlines.items():
        for idx, (cx, cy) in zip(sides, centres[part]):
            a = np.linspace(0, 2 * np.pi, len(idx), endpoint=False)
            marks[idx] = np.stack([cx + 5 * np.cos(a), cy + 3 * np.sin(a)], 1)
    before = np.full((64, 64, 3), 0.5, np.float32)
    brows = before.copy()
    brows[10:23] += 0.25  # the brows' band only
    got = C.part_change(before, brows, marks, outlines)
    assert got["brows"] == pytest.approx(0.25) and got["eyes"] == 0 and got["lips"] == 0
    eyes = before.copy()
    eyes[26:35, 14:27] -= 0.4  # the right eye only: half the eyes' area
    got = C.part_change(before, eyes, marks)
    assert 0.15 < got["eyes"] < 0.25 and got["brows"] == 0 and got["lips"] == 0


def test_edge_change_sees_a_seam_at_the_silhouettes_edge():
    """An edit that repaints the silhouette up to its edge (a seam against the unchanged
    pixels beyond it) shows; one that fades out before the edge does not."""
    mask = np.zeros((40, 40), bool)
    mask[10:30, 10:30] = True
    before = np.full((40, 40, 3), 0.5, np.float32)
    seam = before.copy()
    seam[mask] += 0.2
    inner = before.copy()
    inner[14:26, 14:26] += 0.2
    assert C.edge_change(before, seam, mask, mask) == pytest.approx(0.2)
    assert C.edge_change(before, inner, mask, mask) == 0
    assert C.edge_change(before, inner, mask, mask, width=5) > 0
    grown = mask.copy()
    grown[30:32, 10:30] = True  # an edit whose silhouette is larger: its edge counts
    # the band: 22 x 20 less its 18 x 16 inside; its 2 new rows (40 pixels) unchanged
    assert C.edge_change(before, seam, mask, grown) == pytest.approx(0.2 * 112 / 152)
    empty = np.zeros_like(mask)
    assert np.isnan(C.edge_change(before, seam, empty, empty))


def test_geometry_response_compares_driver_and_render_openings():
    """A render whose mouth follows the driver's at 0.5, whose eyes do not move, and one
    frame where the render has no face."""
    from types import SimpleNamespace

    t = np.linspace(0, 2 * np.pi, 10)
    mouth = 0.2 + 0.15 * np.sin(t)
    drivers = [("d", i) for i in range(10)]
    renders = [("r", i) for i in range(10)]

    def detect(img):
        who, i = img
        if who == "r" and i == 4:
            return None
        m = mouth[i] if who == "d" else 0.05 + 0.5 * mouth[i]
        eyes = 0.1 + 0.05 * np.cos(t[i]) if who == "d" else 0.1
        return SimpleNamespace(landmarks=_face(m, eyes, eyes, 10.0))

    res = C.geometry_response(drivers, renders, detect)
    m = res["measures"]["mouth_open"]
    assert m["correlation"] == pytest.approx(1.0) and m["gain"] == pytest.approx(0.5)
    assert m["detected"] == 9 and np.isnan(m["retracked"][4])
    assert abs(res["measures"]["eye_open_left"]["gain"]) < 1e-9


def test_drive_response_correlates_driving_and_retracked_over_time():
    names = ["jawOpen", "eyeBlinkLeft", "browInnerUp"]
    t = np.linspace(0, 2 * np.pi, 12)
    values = np.stack([0.3 + 0.3 * np.sin(t), 0.5 * (np.cos(t) > 0), np.full(12, 0.2)], 1)

    def render(beta):
        return beta

    def track(img):  # the jaw followed at 0.8, the blink ignored, one frame without a face
        if abs(img[0] - values[3, 0]) < 1e-6:
            return None
        return {"jawOpen": 0.8 * img[0] + 0.1, "eyeBlinkLeft": 0.05}

    res, preds = C.drive_response(render, names, values, track)
    assert len(preds) == 12 and res["frames"] == 12
    jaw = res["controls"]["jawOpen"]
    assert jaw["correlation"] == pytest.approx(1.0) and jaw["gain"] == pytest.approx(0.8)
    assert jaw["detected"] == 11 and np.isnan(jaw["retracked"][3])
    assert abs(res["controls"]["eyeBlinkLeft"]["gain"]) < 1e-9
    assert "browInnerUp" in res["skipped"]  # the driving sequence holds it still


def test_drive_response_renders_the_clamped_sequence_against_the_driver():
    """What is rendered may be clamped (the training range); commanded stays the driver's."""
    names = ["jawOpen"]
    values = np.linspace(0, 1, 6)[:, None]
    rendered = np.clip(values, 0, 0.5)
    seen = []

    def render(beta):
        seen.append(float(beta[0]))
        return beta

    res, _ = C.drive_response(render, names, values, lambda img: {"jawOpen": float(img[0])},
                              rendered=rendered)
    assert seen == pytest.approx(rendered[:, 0].tolist())
    jaw = res["controls"]["jawOpen"]
    assert jaw["commanded"] == pytest.approx(values[:, 0].tolist())
    assert jaw["retracked"] == pytest.approx(rendered[:, 0].tolist())
    assert jaw["gain"] < 0.6  # the clamp shows: the re-tracked value stops at 0.5


def test_driven_response_reads_renders_and_frames_against_their_expressions():
    """Renders that follow the jaw at 0.8 and lose the blink, beside frames the tracker reads
    in full; only controls the training frames vary are read."""
    names = ["jawOpen", "eyeBlinkLeft", "browInnerUp", "notAControl"]
    rng = np.random.default_rng(1)
    values = np.stack([rng.uniform(0, 0.6, 10), rng.uniform(0, 1, 10), np.full(10, 0.1),
                       rng.uniform(0, 1, 10)], 1)
    train = np.stack([rng.uniform(0, 0.6, 30), rng.uniform(0, 1, 30), np.full(30, 0.1),
                      rng.uniform(0, 1, 30)], 1)
    train[:, 2] = np.linspace(0, 0.05, 30)  # browInnerUp barely varies in training
    renders = [np.array([0.8 * v[0], 0.0, v[2]]) for v in values]
    frames = [v[:3].copy() for v in values]

    def track(img):
        return {"jawOpen": float(img[0]), "eyeBlinkLeft": float(img[1]),
                "browInnerUp": float(img[2])}

    res = C.driven_response(renders, frames, values, names, train, track)
    assert set(res["controls"]) == {"jawOpen", "eyeBlinkLeft"}
    assert res["controls"]["jawOpen"]["gain"] == pytest.approx(0.8)
    assert res["controls"]["jawOpen"]["correlation"] == pytest.approx(1.0)
    assert abs(res["controls"]["eyeBlinkLeft"]["gain"]) < 1e-9
    assert res["responding"] == 1 and res["frames"] == 10
    truth = res["truth"]
    assert truth["responding"] == 2
    assert truth["controls"]["eyeBlinkLeft"]["gain"] == pytest.approx(1.0)


@pytest.fixture(scope="module")
def face_scene(tmp_path_factory):
    """The built-in scene at a size the landmarker can read, with its leakage sweep."""
    from flamenerf.synthetic.scene import make_scene

    out = tmp_path_factory.mktemp("face") / "scene"
    return make_scene(out, seed=0, size=128, frames=12, reanimate=2, leakage_steps=2, workers=1)


@pytest.mark.slow
def test_retracker_reads_the_ground_truth_jaw(face_scene):
    from flamenerf.data.dataset import load_dataset

    ds = load_dataset(face_scene)
    sweep = ds.split("leakage")
    neutral = next(f for f in sweep if f.extra.get("leakage_control") in (None, "neutral"))
    jaw = max((f for f in sweep if f.extra.get("leakage_control") == "jawOpen"),
              key=lambda f: f.extra["leakage_value"])
    track = C.Retracker()
    try:
        a, b = track(ds.load_image(neutral)), track(ds.load_image(jaw))
        assert a is not None and b is not None, "no face found in the built-in scene"
        assert b["jawOpen"] > a["jawOpen"] + 0.2  # the open jaw is seen as open
        assert track(np.zeros((64, 64, 3), np.float32)) is None  # no face, no scores
    finally:
        track.close()


@pytest.mark.slow
def test_expressive_region_is_mouth_eyes_and_brows(face_scene):
    from flamenerf.data.dataset import load_dataset

    ds = load_dataset(face_scene)
    part = C.expressive_faces(ds)
    assert 0 < len(part) < 0.8 * len(ds.faces)
    # the region holds the vertices that move most over the frames
    v = ds.face_vertices[[f.position for f in ds.split("train")]]
    v = v - v.mean(1, keepdims=True)
    motion = np.sqrt(((v - v.mean(0)) ** 2).sum(-1).mean(0))
    assert np.argmax(motion) in set(part.ravel())
    assert np.argmin(motion) not in set(part.ravel())


def test_control_figure_rows_are_the_strongest_controls_in_sweep_order():
    from flamenerf.evaluation.protocol import _control_figure

    res = {"controls": {"a": {"commanded": [0, 1, 2], "gain": 0.1},
                        "b": {"commanded": [0, 1, 2], "gain": 0.9},
                        "c": {"commanded": [0, 1, 2], "gain": float("nan")}}}
    renders = [np.full((4, 5, 3), v / 10, np.float32) for v in range(9)]
    img, rows = _control_figure(res, renders, rows=2)
    assert rows == ["b", "a"]
    assert img.shape == (4 * 2 + 2, 5 * 3 + 2 * 2, 3)
    assert img[0, 0, 0] == pytest.approx(0.3) and img[6, 0, 0] == pytest.approx(0.0)


@pytest.mark.slow
def test_ground_truth_renderer_redraws_the_built_in_scene(tiny_scene, toy_dataset):
    """The drive's ground truth: the built-in scene re-rendered at the reference frame's
    camera reproduces that frame for its own β, and opens the mouth for jawOpen; a dataset
    the scene did not make has none."""
    from flamenerf.data.dataset import load_dataset, reference_position
    from flamenerf.data.scene import FrameSet

    ds = load_dataset(tiny_scene)
    ref = ds.frames[reference_position(ds)]
    render = C.ground_truth_renderer(ds, ds.intrinsics)
    own = render(ref.expression)
    image = FrameSet(ds, [ref], ds.intrinsics).images[0].numpy()
    assert own.shape == image.shape and np.abs(own - image).max() < 2 / 255
    jaw = ref.expression.copy()
    jaw[ds.expression_names.index("jawOpen")] = 1.0
    assert np.abs(render(jaw) - own).max() > 0.1  # the mouth opens
    assert C.ground_truth_renderer(load_dataset(toy_dataset), ds.intrinsics) is None


def test_a_sweep_read_by_geometry_follows_only_the_right_way():
    from flamenerf.evaluation.control import geometry_of_sweep

    rng = np.random.default_rng(0)
    base = rng.uniform(0, 100, (468, 2))
    base[[263, 362]] = [[70, 40], [60, 40]]  # the eyes 40 px apart
    base[[33, 133]] = [[30, 40], [20, 40]]
    commanded = np.linspace(0, 1, 5)

    def widened(by: float) -> np.ndarray:
        lm = base.copy()
        lm[61] = [30 - by, 80]
        lm[291] = [60 + by, 80]
        return lm

    wider = [widened(4 * v) for v in commanded]  # up to 0.2 of the eye distance
    smile = geometry_of_sweep("mouthSmileLeft", commanded, wider)
    assert smile["measure"] == "mouth_width" and smile["follows"]
    assert smile["change"] == pytest.approx(8 / 40)
    pucker = geometry_of_sweep("mouthPucker", commanded, wider)  # should narrow it
    assert pucker["measure"] == "-mouth_width" and not pucker["follows"]
    tiny = geometry_of_sweep("mouthSmileLeft", commanded, [widened(0.1 * v) for v in commanded])
    assert tiny["correlation"] > 0.99 and not tiny["follows"]  # jitter-sized
    assert geometry_of_sweep("cheekPuff", commanded, wider) is None  # no plain measure
    assert geometry_of_sweep("jawOpen", commanded, [None] * 4 + [base]) is None
