"""The viewer's capture tracks as filmed: each frame with its own codes, head pose and
mesh, the image `render --split capture` renders for it."""

from __future__ import annotations

import dataclasses
import shlex
import socket
import time

import numpy as np
import pytest
import torch

from flamenerf import cli
from flamenerf.data.head_pose import canonical_from_world
from flamenerf.data.prior import dataset_dilation, mesh_function, prior_mask
from flamenerf.data.video import read_frames
from flamenerf.geometry import se3_log
from flamenerf.images import to_uint8
from flamenerf.model.inference import VIEWER
from flamenerf.rendering.filmed import FilmedClip, changed_meshes
from flamenerf.rendering.reanimate import render_sequence
from flamenerf.data.head_pose import posed_vertices
from flamenerf.training.run import load_run
from flamenerf.viewer.camera import view_intrinsics
from flamenerf.viewer.mask import FaceMasker
from flamenerf.viewer.renderer import RenderWorker


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_a_frame_as_filmed_is_what_render_renders(head_run):
    run = load_run(head_run, "cpu")
    ds = run.dataset(None)
    cap = ds.capture()
    k = len(cap) - 1  # the head turned away from frame 0's pose
    clip = FilmedClip(run, ds, cap)
    T = canonical_from_world(ds, cap)
    assert not np.allclose(T[k], np.eye(4), atol=1e-3)
    c2w, fov = cap[k].c2w, 2 * np.arctan(ds.intrinsics.h / (2 * ds.intrinsics.fy))
    intr = view_intrinsics(fov, ds.intrinsics.w / ds.intrinsics.h, 32)
    w, a = run.clip_codes(ds, cap)
    values = ds.expression_matrix(cap)
    edited = values[k].copy()
    edited[run.expression_names.index("jawOpen")] = 0.0  # it is open (0.9)
    # the plan of `render --split capture [--edit]` for frame k: its own codes, head twist
    # and mesh (moved by the edit)
    mesh_of = mesh_function(run.model, ds)
    canon = clip.canonical[k:k + 1]
    want = {}
    for name, e in (("own", values[k]), ("edited", edited)):
        verts = posed_vertices(changed_meshes(canon, mesh_of, e[None], values[k:k + 1]), T[k:k + 1])
        ref, = render_sequence(run.model, ds, intr, c2w[None], e[None], verts, w[k:k + 1],
                               a[k:k + 1], dataset_dilation(ds), heads=se3_log(T[k:k + 1]),
                               settings=dataclasses.replace(VIEWER, warp_grid=0))
        want[name] = ref
    assert np.array_equal(want["own"].mask, prior_mask(ds, ds.face_vertices[cap[k].position],
                                                       c2w, intr))  # the tracked mesh itself
    assert (want["own"].mask != want["edited"].mask).any()  # the jaw closed

    shown = []
    wk = RenderWorker(run.model, *run.frame_codes(0), FaceMasker(ds, 0, run.model),
                      values[k], lambda key, f: shown.append(f), height=32, settle_s=0.01)
    wk.set_quality(progressive=False)
    wk.start()
    try:
        wk.set_camera("a", c2w, fov, ds.intrinsics.w / ds.intrinsics.h)
        assert wk.wait_idle(30)
        first = shown[-1]
        assert first.extras["filmed"] is None
        wk.set_filmed(clip.frame(k), values[k])
        assert wk.wait_idle(30)
        got = shown[-1]
        assert got.extras["filmed"] == k and got.extras["rays"] == 32 * intr.w  # new codes
        assert np.array_equal(got.extras["mask"], want["own"].mask)
        assert np.abs(got.image.astype(int) - to_uint8(want["own"].rgb).astype(int)).max() <= 1
        assert np.abs(got.image.astype(int) - first.image.astype(int)).max() >= 3  # toy: 6
        n = len(shown)
        wk.set_filmed(clip.frame(k), values[k])  # the same frame again: nothing to do
        wk.set_expression(edited)  # a slider: the frame's look, the jaw moved
        assert wk.wait_idle(30)
        got = shown[-1]
        assert len(shown) == n + 1 and got.extras["rays"] < 32 * intr.w  # the face again only
        assert np.array_equal(got.extras["mask"], want["edited"].mask)
        assert np.abs(got.image.astype(int) - to_uint8(want["edited"].rgb).astype(int)).max() <= 1
        assert not wk.errors
    finally:
        wk.stop()


@pytest.mark.slow
def test_the_viewer_plays_the_capture_as_filmed(head_run, tmp_path):
    from flamenerf.viewer.app import Viewer
    from flamenerf.viewer.options import ViewerOptions

    run = load_run(head_run, "cpu")
    v = Viewer(run, ViewerOptions(port=_free_port(), resolution=16, verbose=False))
    v.start()
    try:
        cap = next(t for t in v.tracks if t.name.startswith("capture"))
        tour = next(t for t in v.tracks if t.name.startswith("tour"))
        assert cap.name in v.filmable and tour.name not in v.filmable and v.g_filmed.value
        v.g_track.value = cap.name
        assert v.worker.filmed().index == 0
        v.show_track_frame(cap, 5)
        f = v.worker.filmed()
        w, _ = run.clip_codes(v.ds, cap.clip)
        assert f.index == 5 and torch.equal(f.omega, w[5])
        assert f.head is not None  # the frame's own head pose
        v.set_edit("jawOpen+=0.2")  # the Edit box: the same frame, its expression edited
        jaw = run.expression_names.index("jawOpen")
        assert v.worker.filmed().index == 5
        assert v.worker.expression()[jaw] > v.shown(cap.frames[5])[jaw]
        v.g_filmed.value = False  # frame 0's codes, the frame's own head and mesh
        f = v.worker.filmed()
        assert f.index == 5 and not f.own_codes and torch.equal(f.omega, v.worker.omega)
        assert f.head is not None
        v.g_filmed.value = True
        assert v.worker.filmed().index == int(v.g_frame.value)
        # what the viewer shows, as a render command that runs
        v.set_head_pose(10, 0, 0)
        v.g_filmed.value = False
        cmd = v.render_command()
        assert "Render it: `flamenerf render" in v.g_command.content
        args = shlex.split(cmd)
        assert args[:2] == ["flamenerf", "render"] and "--split" in args
        assert args[args.index("--edit") + 1] == "jawOpen+=0.2"
        assert args[args.index("--codes") + 1] == "first"
        # render eases --head-pose keyframes: the sliders' held turn is said, not passed
        assert "--head-pose" not in args and "head sliders" in v.g_command.content
        out = tmp_path / "viewer.mp4"
        assert cli.main(args[1:] + ["--max-frames", "2", "--size", "16", "--out", str(out),
                                    "--device", "cpu", "--no-sound"]) == 0
        assert len(read_frames(out)) == 2
        v.set_head_pose(0, 0, 0)
        v.g_filmed.value = True
        assert "--codes" not in v.render_command() and "head sliders" not in v.g_command.content
        v.show_frame0()  # the "Frame 0 expression" button: frame 0's look and head again
        assert v.worker.filmed() is None
        assert np.allclose(v.worker.expression(), v.shown(v.frame0_expression))
        v.show_track_frame(cap, 3)
        to = v.frame_camera()  # "Camera of this frame": where frame 3 was filmed from
        assert np.allclose(to.c2w, cap.clip[3].c2w) and to.frame_position == cap.clip[3].position
        v.g_track.value = tour.name  # not the clip's frames
        assert v.worker.filmed() is None
        assert v.frame_camera() is None
    finally:
        v.stop()


@pytest.mark.slow
def test_a_reanimation_splits_frame_is_what_render_renders(head_run, tmp_path):
    """A split whose frames have no codes (the built-in scene's novel head poses): the
    viewer shows each frame with frame 0's codes and its own head pose and mesh, as
    `render --split novel_pose` does; before, frame 0's head and the model's mesh."""
    from flamenerf.rendering.videos import RenderOptions, plan_render
    from flamenerf.viewer.app import Viewer
    from flamenerf.viewer.options import ViewerOptions

    run = load_run(head_run, "cpu")
    v = Viewer(run, ViewerOptions(port=_free_port(), resolution=32, verbose=False))
    v.worker.set_quality(progressive=False)
    shown = []
    v.worker.display = lambda key, f: shown.append(f)
    v.worker.start()
    try:
        t = next(t for t in v.tracks if t.name.startswith("split novel_pose"))
        assert t.name not in v.filmable
        plan = plan_render(RenderOptions(head_run, out=tmp_path / "x.mp4", split="novel_pose",
                                         device="cpu"), log=lambda _: None)
        k = t.num_frames - 1
        fr = t.clip[k]
        fov = 2 * np.arctan(v.ds.intrinsics.h / (2 * v.ds.intrinsics.fy))
        aspect = v.ds.intrinsics.w / v.ds.intrinsics.h
        v.worker.set_camera("a", fr.c2w, fov, aspect)
        v.show_track_frame(t, k, sync=False)
        f = v.worker.filmed()
        assert f.index == k and not f.own_codes and torch.equal(f.omega, v.worker.omega)
        assert not np.allclose(f.head, np.eye(4), atol=1e-3)  # the head turned
        assert v.worker.wait_idle(30)
        got = shown[-1]
        assert got.extras["filmed"] == k and not got.extras["own_codes"]
        intr = view_intrinsics(fov, aspect, 32)
        want, = render_sequence(run.model, v.ds, intr, fr.c2w[None], plan.values[k:k + 1],
                                plan.verts[k:k + 1], *run.frame_codes(0), plan.dilate_px,
                                heads=plan.heads[k:k + 1],
                                settings=dataclasses.replace(VIEWER, warp_grid=0))
        assert np.array_equal(got.extras["mask"], want.mask)
        assert np.abs(got.image.astype(int) - to_uint8(want.rgb).astype(int)).max() <= 1
    finally:
        v.worker.stop()


@pytest.mark.slow
def test_the_edit_boxes_and_pause_show_what_they_say(head_run):
    """With an edit in force, unticking "Stay within the clip's range" shows the frame
    edited beyond it at once (the command changed, the picture kept the clamp); Pause
    leaves the Frame slider and the expression sliders on the frame last shown."""
    from flamenerf.viewer.app import Viewer
    from flamenerf.viewer.options import ViewerOptions

    run = load_run(head_run, "cpu")
    v = Viewer(run, ViewerOptions(port=_free_port(), resolution=16, verbose=False))
    v.start()
    try:
        cap = next(t for t in v.tracks if t.name.startswith("capture"))
        assert v.tracks[0].name.startswith("tour") and v.g_filmed.disabled  # the first shown
        v.g_track.value = cap.name
        v.show_track_frame(cap, 2)
        jaw = run.expression_names.index("jawOpen")
        v.set_edit("jawOpen+=3")
        clamped = float(v.worker.expression()[jaw])
        assert clamped <= v.range.hi[jaw] + 1e-6 and clamped < v.hi - 0.05
        v.g_within.value = False  # then only the sliders' own range holds it
        assert float(v.worker.expression()[jaw]) == pytest.approx(v.hi), \
            "the picture follows the box"
        assert "--extrapolate" in v.render_command()
        v.g_within.value = True
        assert float(v.worker.expression()[jaw]) == pytest.approx(clamped)
        v.set_edit("")
        # a slider moved by hand: the view is no longer the track's frame, and Render it says so
        from types import SimpleNamespace

        v._slider_cb(jaw)(SimpleNamespace(client=object(), target=SimpleNamespace(value=0.3)))
        assert "expression sliders' change not in it" in v.g_command.content
        v.show_track_frame(cap, 2)
        assert "not in it" not in v.g_command.content
        tour = next(t for t in v.tracks if t.name.startswith("tour"))
        v.g_track.value = tour.name
        assert v.g_filmed.disabled  # As filmed means nothing for the tour's frames
        v.g_track.value = cap.name
        assert not v.g_filmed.disabled
        v.g_loop.value = True
        v.play()
        deadline = time.monotonic() + 20
        while (v._played is None or v._played[0] < 3) and time.monotonic() < deadline:
            time.sleep(0.05)
        v.toggle_play()  # the Pause button
        shown = v.worker.filmed().index
        assert not v.playing and int(v.g_frame.value) == shown == v._played[0]
        np.testing.assert_allclose([s.value for s in v.g_sliders], v.worker.expression(),
                                   atol=1e-4)
    finally:
        v.stop()
