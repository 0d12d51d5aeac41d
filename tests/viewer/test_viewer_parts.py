"""The viewer's parts without a browser: tracks, cameras, the progressive render worker."""

from __future__ import annotations

import json

import numpy as np
import pytest

from flamenerf.data.dataset import load_dataset
from flamenerf.errors import UserError
from flamenerf.synthetic.render import mask_dilation
from flamenerf.viewer.camera import c2w_from_viser, home_camera, view_intrinsics
from flamenerf.data.prior import dataset_dilation, estimate_dilation
from flamenerf.viewer.mask import FaceMasker
from flamenerf.viewer.renderer import RenderWorker
from flamenerf.viewer.tracks import dataset_tracks, load_track_file, slider_range, tour_track


def test_camera_conversion():
    # viser: OpenCV axes. A camera at +z looking at the origin with +y up (OpenGL c2w
    # rotation = I) has OpenCV rotation diag(1, -1, -1) = quaternion (w, x, y, z) = (0, 1, 0, 0).
    c2w = c2w_from_viser(np.array([0.0, 1.0, 0.0, 0.0]), np.array([0.0, 0.0, 2.0]))
    assert np.allclose(c2w[:3, :3], np.eye(3)) and np.allclose(c2w[:3, 3], [0, 0, 2])
    intr = view_intrinsics(np.deg2rad(90), 2.0, 100)
    assert (intr.w, intr.h) == (200, 100) and np.isclose(intr.fy, 50) and intr.cx == 100


def test_home_camera_is_frame_0(tiny_scene):
    ds = load_dataset(tiny_scene)
    h = home_camera(ds)
    f0 = ds.frames[h.frame_position]
    assert f0.frame_index == 0 and np.allclose(h.c2w, f0.c2w)
    fwd = (h.look_at - h.position) / np.linalg.norm(h.look_at - h.position)
    assert np.allclose(fwd, -f0.c2w[:3, 2], atol=1e-9)  # looks along frame 0's axis
    assert np.isclose(np.tan(h.fov_y / 2) * ds.intrinsics.fy * 2, ds.intrinsics.h)
    # the mask the viewer rasterises at the dataset's camera is the dataset's mask
    m = FaceMasker(ds, h.frame_position)(ds.intrinsics, f0.c2w)
    stored = ds.load_mask(f0)
    assert np.mean(m != stored) < 0.01
    # ... grown by the dilation the scene was made with
    assert dataset_dilation(ds) == mask_dilation(ds.intrinsics)
    # a stored mask says the same, for datasets written before the dilation was stored
    assert estimate_dilation(ds, h.frame_position) == mask_dilation(ds.intrinsics)


def test_tracks(tiny_scene, tmp_path):
    ds = load_dataset(tiny_scene)
    tracks = dataset_tracks(ds)
    cap = tracks[0]
    assert cap.name.startswith("capture") and cap.frames.shape[1] == ds.expression_dim
    assert cap.num_frames == sum(f.frame_index is not None for f in ds.frames)
    assert any(t.name.startswith("split reanimate") for t in tracks)
    assert slider_range(ds) == (0.0, 1.0)
    # the tour: `render --expressions tour`'s sequence, from the base given
    base = ds.frames[0].expression.astype(np.float32)
    tour = tour_track(ds, ds.expression_names, base)
    assert tour.name.startswith("tour") and tour.fps == 30 and tour.num_frames % 24 == 1
    assert np.allclose(tour.frames[0], base) and np.abs(tour.frames - base).max() > 0.1
    assert tour_track(ds, ds.expression_names[::-1], base) is None  # not the run's controls
    # the capture plays each frame once, a frame before a gap in the clip for the gap's
    # time (as `render --split capture` holds it)
    assert cap.shown is None and cap.frame_at(2, 0.0, False) == (2, False)
    capture = [f for f in ds.frames if f.frame_index is not None]
    times = np.arange(len(capture)) / 10.0
    times[3:] += 0.4  # 0.4 s more after the third frame: shown 5 ticks at 10 fps
    for f, t in zip(sorted(capture, key=lambda f: f.frame_index), times):
        f.extra["time"] = float(t)
    gap = dataset_tracks(ds)[0]
    assert gap.fps == 10.0 and gap.shown[:5].tolist() == [1, 1, 5, 1, 1]
    assert gap.duration() == pytest.approx((len(capture) + 4) / 10)
    assert [gap.frame_at(0, s / 10 + 0.01, False)[0] for s in range(9)] == [0, 1, 2, 2, 2, 2,
                                                                           2, 3, 4]
    assert gap.frame_at(4, 0.05, False) == (4, False)
    assert gap.frame_at(0, 100.0, False) == (len(capture) - 1, True)
    assert gap.frame_at(0, gap.duration() + 0.01, True) == (0, False)

    names = ds.expression_names
    p = tmp_path / "drive.json"
    # other order, one unknown channel, one missing control
    file_names = ["somethingElse"] + names[::-1][:-1]
    rows = [[0.5] + [float(i) / 10 for i in range(len(names) - 1)]]
    p.write_text(json.dumps({"names": file_names, "fps": 25, "frames": rows}))
    t = load_track_file(p, names)
    assert t.fps == 25 and t.frames.shape == (1, len(names))
    for k, n in enumerate(file_names[1:]):
        assert t.frames[0, names.index(n)] == pytest.approx(rows[0][k + 1])
    assert t.frames[0, names.index(names[0])] == 0  # not in the file
    p.write_text(json.dumps({"names": ["a", "b"], "frames": [[0, 1]]}))
    with pytest.raises(UserError, match="none of its 2 expression channels"):
        load_track_file(p, names)


@pytest.mark.slow
def test_worker_renders_coarse_to_fine_and_follows_changes(tiny_run):
    from flamenerf.training.run import load_run

    run = load_run(tiny_run, device="cpu")
    ds = run.dataset()
    h = home_camera(ds)
    frames = []
    w, a = run.frame_codes(0)
    wk = RenderWorker(run.model, w, a, FaceMasker(ds, h.frame_position),
                      np.zeros(len(run.expression_names)), lambda k, f: frames.append(f),
                      height=16, settle_s=0.05)
    wk.start()
    try:
        wk.set_camera("a", h.c2w, h.fov_y, 1.5)
        assert wk.wait_idle(30)
        assert [f.intr.h for f in frames] == [8, 16] and frames[-1].final
        assert [f.count for f in frames] == [1, 2] and frames[-1].intr.w == 24
        n = len(frames)
        wk.set_camera("a", h.c2w, h.fov_y, 1.5)  # unchanged: nothing to do
        e = wk.expression()
        e[0] = 1.0
        wk.set_expression(e)
        assert wk.wait_idle(30)
        new = frames[n:]
        # the camera is that of the last full image: only the silhouette's pixels again,
        # at the full height at once
        assert [f.intr.h for f in new] == [16] and new[0].final
        mask = new[-1].extras["mask"]
        assert 0 < new[-1].extras["rays"] < 16 * 24 and mask.sum() <= new[-1].extras["rays"]
        diff = np.abs(new[-1].image.astype(int) - frames[n - 1].image.astype(int)).max(-1)
        assert diff[~mask].max() <= 1 and diff[mask].max() > 3
        wk.refresh("a")  # the whole image again, coarse to fine: what the pixels reused match
        assert wk.wait_idle(30)
        assert [f.intr.h for f in frames[n + 1:]] == [8, 16]
        assert frames[-1].extras["rays"] == 16 * 24
        assert np.abs(frames[-1].image.astype(int) - new[-1].image.astype(int)).max() <= 1
        wk.partial_max = 0.0  # as for a face that fills the view: coarse to fine, and the
        n = len(frames)       # last level renders the silhouette's pixels alone
        e[0] = 0.5
        wk.set_expression(e)
        assert wk.wait_idle(30)
        assert [f.intr.h for f in frames[n:]] == [8, 16]
        assert 0 < frames[-1].extras["rays"] < 16 * 24
        run.model.cfg.expression_mode = "everywhere"  # the no-prior ablation: β reaches
        n = len(frames)                               # every ray, nothing is kept
        e[0] = 0.0
        wk.set_expression(e)
        assert wk.wait_idle(30)
        assert [f.intr.h for f in frames[n:]] == [8, 16]
        assert frames[-1].extras["rays"] == 16 * 24
        run.model.cfg.expression_mode = "masked"
        wk.set_mode("Depth")
        wk.set_quality(progressive=False)
        assert wk.wait_idle(30)
        assert frames[-1].mode == "Depth" and frames[-1].level == 0 and frames[-1].final
        assert frames[-1].image.shape == (16, 24, 3) and "depth_range" in frames[-1].extras
        assert not wk.errors
    finally:
        wk.stop()


def test_zoomed_out_view_renders(tiny_run):
    """Scrolling out in the viewer puts samples far outside the training cameras' box."""
    import torch

    from flamenerf.model.render_image import render_image
    from flamenerf.training.run import load_run

    run = load_run(tiny_run, device="cpu")
    ds = run.dataset()
    h = home_camera(ds)
    c2w = h.c2w.copy()
    c2w[:3, 3] = h.look_at + 3.0 * (h.position - h.look_at)
    intr = view_intrinsics(h.fov_y, 1.0, 16)
    w, a = run.frame_codes(0)
    mask = FaceMasker(ds, h.frame_position)(intr, c2w)
    out = render_image(run.model, intr, c2w, w, a, torch.zeros(ds.expression_dim), mask)
    assert torch.isfinite(out["rgb"]).all()


def test_viewer_controls_without_a_browser(tiny_run, tmp_path):
    """Track selection, playback, pause, neutral and frame-0 buttons drive the shared
    expression (no page connected, so nothing renders)."""
    import socket
    import time

    from flamenerf.training.run import load_run
    from flamenerf.viewer.app import Viewer
    from flamenerf.viewer.options import ViewerOptions

    run = load_run(tiny_run, device="cpu")
    names = run.expression_names
    drive = tmp_path / "drive.json"
    rows = [[(k + 1) / 10 if j == 0 else 0.0 for j in range(len(names))] for k in range(5)]
    drive.write_text(json.dumps({"names": names, "fps": 20, "frames": rows}))
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    v = Viewer(run, ViewerOptions(port=port, resolution=16, track=(drive,), verbose=False))
    v.start()
    try:
        assert v.tracks[0].name.startswith("file drive.json")
        assert v.g_track.value == v.tracks[0].name
        assert [s.label for s in v.g_sliders] == names
        v.play()
        time.sleep(0.6)
        assert v.playing
        v.pause()
        e = v.worker.expression()
        # a file's expressions are clamped to the training range, as `render --expressions`
        assert not v.playing and any(np.allclose(e, v.shown(r))
                                     for r in np.asarray(rows, np.float32))
        time.sleep(0.3)
        assert np.array_equal(v.worker.expression(), e)  # paused: stays
        assert v.tracks[1].name.startswith("tour")  # the tour, then the capture
        v.g_track.value = v.tracks[2].name
        assert v.tracks[2].name.startswith("capture")
        assert v.g_frame.max == v.tracks[2].num_frames - 1
        assert np.allclose(v.worker.expression(), v.tracks[2].frames[0])
        v.set_expression(v.neutral)  # zeros, within the training frames' range
        want = v.range.clamp(np.zeros(len(names), np.float32))
        assert np.allclose(v.worker.expression(), want)
        assert np.allclose([s.value for s in v.g_sliders], want, atol=1e-4)
        v.set_expression(v.frame0_expression)
        assert np.allclose([s.value for s in v.g_sliders], v.frame0_expression, atol=1e-4)
        # the Edit box changes every frame of the track, as `render --edit` does
        jaw = names.index("jawOpen")
        v.g_frame.value = 3
        v.set_edit("jawOpen*=0, browInnerUp += 0.05")
        want = v.tracks[2].frames[3].copy()
        want[jaw] = 0
        want[names.index("browInnerUp")] += 0.05
        assert np.allclose(v.worker.expression(), v.range.clamp(want), atol=1e-6)
        assert "editing jawOpen*=0" in v.g_edit_note.content
        v.set_edit("jawOpn=1")  # a typo: said, and the last good edit stays
        assert "unknown control 'jawOpn'" in v.g_edit_note.content
        assert np.allclose(v.track_frames(v.tracks[2])[:, jaw], v.range.lo[jaw])  # clamped
        v.set_edit("")
        assert v.track_frames(v.tracks[2]) is v.tracks[2].frames
        # a file's frames are clamped to the training range before the edit, as render's
        from flamenerf.rendering.edits import apply_edits, parse_edits

        from flamenerf.viewer.tracks import Track

        far = np.tile(v.range.hi, (2, 1)).astype(np.float32)
        far[:, jaw] += 1.0  # beyond the range: jawOpen-=0.3 lowers it from the range's top
        v.set_edit("jawOpen-=0.3")
        got = v.track_frames(Track("file far.json (2 frames)", far, 20.0))
        want = apply_edits(v.range.clamp(far), parse_edits(["jawOpen-=0.3"], names),
                           v.companions, v.range)[0]
        assert np.allclose(got, want) and np.allclose(got[:, jaw], v.range.hi[jaw] - 0.3)
    finally:
        v.stop()


def test_masker_poses_the_mesh_by_the_head_pose(tiny_scene):
    from flamenerf.data.head_pose import HeadPoseKey, control_transform, head_region

    ds = load_dataset(tiny_scene)
    masker = FaceMasker(ds, 0)
    intr, c2w = ds.intrinsics, ds.frames[0].c2w
    still = masker(intr, c2w, None)
    assert np.array_equal(masker(intr, c2w, None, np.eye(4)), still)
    T = control_transform(HeadPoseKey(yaw=35, x=0.02), head_region(ds))
    turned = masker(intr, c2w, None, T)
    assert turned.any() and (turned != still).mean() > 0.01


def test_a_slider_moves_its_companions_unless_unticked(tiny_run):
    """With companions (an ARKit dataset's; made by hand here for the tiny run's controls)
    dragging control 0 moves control 1 along; unticking "Move companions" stops it."""
    import socket
    from types import SimpleNamespace

    from flamenerf.data.companions import Companions
    from flamenerf.training.run import load_run
    from flamenerf.viewer.app import Viewer
    from flamenerf.viewer.options import ViewerOptions

    run = load_run(tiny_run, device="cpu")
    names = run.expression_names
    rng = np.random.default_rng(0)
    train = rng.uniform(0, 0.2, (30, len(names)))
    train[:, 0] = rng.uniform(0, 1, 30)
    train[:, 1] = 0.5 * train[:, 0]
    follows = np.zeros((len(names), len(names)), bool)
    follows[0, 1] = True
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    v = Viewer(run, ViewerOptions(port=port, resolution=16, verbose=False))
    v.companions = Companions(list(names), follows, train)
    v.range = None  # not what this test is about: any value, as given
    v.start()
    try:
        v.set_expression(v.neutral)
        drag = v._slider_cb(0)
        drag(SimpleNamespace(client=object(), target=SimpleNamespace(value=0.4)))
        e = v.worker.expression()
        assert e[0] == pytest.approx(0.4) and e[1] == pytest.approx(0.2, abs=0.01)
        assert v.g_sliders[1].value == pytest.approx(e[1], abs=1e-3)
        tour = next(t for t in v.tracks if t.name.startswith("tour"))
        v.g_companions.value = False
        drag(SimpleNamespace(client=object(), target=SimpleNamespace(value=0.8)))
        e2 = v.worker.expression()
        assert e2[0] == pytest.approx(0.8) and e2[1] == pytest.approx(e[1])
        # the tour without companions too, as render's with --no-companions
        alone = tour_track(v.ds, names, v.frame0_expression, None).frames
        assert np.array_equal(tour.frames, alone)
        v.g_companions.value = True
        assert np.array_equal(tour.frames, tour_track(v.ds, names, v.frame0_expression,
                                                      v.companions).frames)
        assert not np.array_equal(tour.frames, alone)
    finally:
        v.stop()


def test_a_slider_stops_at_the_training_range_unless_unticked(tiny_run):
    """Dragging a control past what the training frames show stops it there (the slider
    too); unticking "Stay within the clip's range" lets it through."""
    import socket
    from types import SimpleNamespace

    from flamenerf.data.expression_range import ExpressionRange
    from flamenerf.training.run import load_run
    from flamenerf.viewer.app import Viewer
    from flamenerf.viewer.options import ViewerOptions

    run = load_run(tiny_run, device="cpu")
    names = run.expression_names
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    v = Viewer(run, ViewerOptions(port=port, resolution=16, verbose=False))
    assert v.range is not None  # the run's own dataset: its training range
    v.range = ExpressionRange(list(names), np.zeros(len(names)), np.full(len(names), 0.3))
    v.companions = None
    v.start()
    try:
        v.set_expression(v.neutral)
        drag = v._slider_cb(0)
        drag(SimpleNamespace(client=object(), target=SimpleNamespace(value=0.8)))
        assert v.worker.expression()[0] == pytest.approx(0.3)
        assert v.g_sliders[0].value == pytest.approx(0.3)
        drag(SimpleNamespace(client=object(), target=SimpleNamespace(value=0.2)))
        assert v.worker.expression()[0] == pytest.approx(0.2)
        v.g_within.value = False
        drag(SimpleNamespace(client=object(), target=SimpleNamespace(value=0.8)))
        assert v.worker.expression()[0] == pytest.approx(0.8)
    finally:
        v.stop()


@pytest.mark.slow
def test_status_says_when_the_camera_leaves_the_capture(tiny_run):
    """At frame 0's camera the status line says nothing more; well away from every training
    camera it says how far (views there extrapolate)."""
    from types import SimpleNamespace

    from flamenerf.training.run import load_run
    from flamenerf.viewer.app import Viewer
    from flamenerf.viewer.options import ViewerOptions

    run = load_run(tiny_run, device="cpu")
    v = Viewer(run, ViewerOptions(port=1, resolution=16, verbose=False))  # never started
    at_home = SimpleNamespace(camera=SimpleNamespace(position=v.home.position))
    assert v.capture_note(at_home) == ""
    far = v.home.position + 0.5 * v.home.up  # half a metre above frame 0's camera
    note = v.capture_note(SimpleNamespace(camera=SimpleNamespace(position=far)))
    assert note.startswith(" · outside the capture (") and "cm from its cameras" in note


def test_a_failed_image_says_what_to_do(tiny_run):
    """A render that fails says so on the status line; a lost GPU context (every image
    after it would fail too) says how to start again without the Triton kernels."""
    from types import SimpleNamespace

    from flamenerf.training.run import load_run
    from flamenerf.viewer.app import Viewer
    from flamenerf.viewer.options import ViewerOptions

    run = load_run(tiny_run, device="cpu")
    v = Viewer(run, ViewerOptions(port=1, resolution=16, verbose=False))  # never started
    v._status[7] = status = SimpleNamespace(content="")
    v._render_failed(7, ValueError("bad β"))
    assert "failed (ValueError: bad β); see the terminal" in status.content
    v._render_failed(7, RuntimeError("CUDA error: an illegal memory access was encountered"))
    assert "illegal memory access" in status.content
    assert "restart the viewer with FLAMENERF_GPU_KERNELS=0" in status.content


@pytest.mark.slow
def test_the_first_image_of_a_change_is_always_shown(tiny_run):
    """A state that changes again while its image renders (a track playing faster than
    the renderer) still gets that image shown, with Progressive off too, and an expression
    change under the same camera starts at half the height, a camera move at a quarter."""
    from flamenerf.training.run import load_run

    run = load_run(tiny_run, device="cpu")
    ds = run.dataset()
    h = home_camera(ds)
    frames = []
    masker = FaceMasker(ds, h.frame_position)
    moves = []  # expressions a 'player' sets while the worker renders

    def busy_masker(*args):
        if moves:
            wk.set_expression(moves.pop(0))
        return masker(*args)

    w, a = run.frame_codes(0)
    e = np.zeros(len(run.expression_names), np.float32)
    wk = RenderWorker(run.model, w, a, busy_masker, e, lambda k, f: frames.append(f),
                      height=64, settle_s=0.05)
    wk.partial_max = 0.0  # whole images after an expression change too
    wk.start()
    try:
        wk.set_camera("a", h.c2w, h.fov_y, 1.0)
        assert wk.wait_idle(60)
        assert [f.intr.h for f in frames] == [16, 32, 64]  # a new camera: from a quarter
        n = len(frames)
        wk.set_expression(e + 0.5)
        assert wk.wait_idle(60)
        assert [f.intr.h for f in frames[n:]] == [32, 64]  # same camera: from half
        for progressive in (True, False):  # the silhouette's pixels alone; whole images
            wk.partial_max = 1.0 if progressive else 0.0
            wk.set_quality(progressive=progressive)
            assert wk.wait_idle(60)
            n = len(frames)
            start = e + (0.0 if progressive else 1.0)
            moves.extend([start + 0.1, start + 0.2, start + 0.3])
            wk.set_expression(start)
            assert wk.wait_idle(60)
            # every image rendered was shown though its state moved on while it rendered
            assert len(frames) - n == 4 and all(f.intr.h == 64 for f in frames[n:])
            assert np.allclose(wk.expression(), start + 0.3) and not wk.errors
    finally:
        wk.stop()
