"""`flamenerf render` writes playable videos with the requested number of frames."""

from __future__ import annotations

import numpy as np
import pytest

from flamenerf.commands.render import render
from flamenerf.rendering.videos import RenderOptions
from flamenerf.data.dataset import load_dataset
from flamenerf.errors import UserError
from flamenerf.data.prior import estimate_dilation, prior_mask
from flamenerf.data.video import read_frames


@pytest.mark.slow
def test_orbit_with_depth_and_side_by_side(toy_run, tmp_path):
    out = tmp_path / "v.mp4"
    render(RenderOptions(toy_run, out=out, expressions=["jawOpen=1"], camera="orbit", frames=5,
                         depth=True, side_by_side=True, device="cpu"))
    for name, min_w in (("v.mp4", 16), ("v_depth.mp4", 16), ("v_sbs.mp4", 3 * 16)):
        frames = read_frames(tmp_path / name)
        assert len(frames) == 5, name
        # 16 px panels are too narrow for their titles: none
        assert frames[0].shape[0] == 16 and frames[0].shape[1] >= min_w
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.mp4", "v_depth.mp4", "v_sbs.mp4"]
    # the orbit moves the camera, so frames differ
    f = read_frames(out)
    assert np.abs(f[0].astype(int) - f[2].astype(int)).mean() > 0


@pytest.mark.slow
def test_split_and_file_sources_set_the_length(toy_run, tmp_path):
    render(RenderOptions(toy_run, out=tmp_path / "s.mp4", split="reanimate", device="cpu"))
    assert len(read_frames(tmp_path / "s.mp4")) == 2
    np.save(tmp_path / "e.npy", np.random.default_rng(0).uniform(size=(4, 3)))
    render(RenderOptions(toy_run, out=tmp_path / "e.mp4", expressions=[str(tmp_path / "e.npy")],
                         camera="spiral", size=20, device="cpu"))
    frames = read_frames(tmp_path / "e.mp4")
    assert len(frames) == 4 and frames[0].shape[:2] == (20, 20)
    # the tour: 24 frames (and one) for each control the training frames vary
    render(RenderOptions(toy_run, out=tmp_path / "t.mp4", expressions=["tour"], device="cpu"))
    assert len(read_frames(tmp_path / "t.mp4")) % 24 == 1


@pytest.mark.slow
def test_bad_inputs_are_user_errors(toy_run, tmp_path):
    with pytest.raises(UserError, match="nope: run directory does not exist"):
        render(RenderOptions(tmp_path / "nope"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match="empty: not a run directory"):
        render(RenderOptions(tmp_path / "empty"))
    with pytest.raises(UserError, match="--camera 'orbitt': neither a camera path"):
        render(RenderOptions(toy_run, out=tmp_path / "x.mp4", camera="orbitt", device="cpu"))
    with pytest.raises(UserError, match="unknown control 'jawOpn'"):
        render(RenderOptions(toy_run, out=tmp_path / "x.mp4", expressions=["jawOpn=0.8"],
                             device="cpu"))
    with pytest.raises(UserError, match="missing.json: expression file does not exist"):
        render(RenderOptions(toy_run, out=tmp_path / "x.mp4",
                             expressions=[str(tmp_path / "missing.json")], device="cpu"))
    with pytest.raises(UserError, match="one expression source"):
        render(RenderOptions(toy_run, expressions=["jawOpen=1"], split="reanimate"))
    (tmp_path / "taken.mp4").write_bytes(b"")
    with pytest.raises(UserError, match="taken.mp4: already exists"):
        render(RenderOptions(toy_run, out=tmp_path / "taken.mp4", device="cpu"))
    assert not (tmp_path / "x.mp4").exists()
    # folders made for the videos go again when the render fails
    with pytest.raises(UserError, match="unknown control 'jawOpn'"):
        render(RenderOptions(toy_run, out=tmp_path / "new" / "deeper" / "x.mp4",
                             expressions=["jawOpn=0.8"], device="cpu"))
    assert not (tmp_path / "new").exists()


def test_prior_mask_reproduces_the_dataset_masks(toy_dataset):
    ds = load_dataset(toy_dataset)
    dil = estimate_dilation(ds)
    assert dil == 1  # the toy's masks are dilated by one pixel
    for fr in ds.split("train"):
        m = prior_mask(ds, ds.face_vertices[fr.position], fr.c2w, ds.intrinsics, dil)
        np.testing.assert_array_equal(m, ds.load_mask(fr))
    small = prior_mask(ds, ds.face_vertices[0], ds.frames[0].c2w, ds.intrinsics.scaled(0.5), 1)
    assert small.shape == (8, 8) and small.any()


@pytest.mark.slow
def test_controls_beyond_the_training_range_are_clamped_unless_asked(toy_run, tmp_path):
    """jawOpen=5 renders as the largest jawOpen the training frames show, with a note;
    --extrapolate renders it as given (the values handed to the renderer: the toy run,
    trained 2 steps, barely responds to β, so its pixels cannot tell)."""
    from flamenerf.data.expression_range import training_range
    from flamenerf.rendering import videos
    from flamenerf.training.run import load_run

    ds = load_run(toy_run, "cpu").dataset()
    rng = training_range(ds)
    jaw = rng.names.index("jawOpen")
    hi = rng.hi[jaw]
    assert 0 < hi < 5

    def frames(value, extrapolate=False):
        notes = []
        out = tmp_path / f"{value}_{extrapolate}.mp4"
        videos.render_videos(RenderOptions(toy_run, out=out, expressions=[f"jawOpen={value}"],
                                           frames=3, extrapolate=extrapolate, device="cpu"),
                             log=notes.append)
        return np.stack(read_frames(out)).astype(int), notes

    clamped, notes = frames(5)
    assert any("clamped" in n and "jawOpen 5.00 asked, " in n for n in notes)
    at_hi, notes_hi = frames(f"{hi:.6f}")
    assert not any("clamped" in n for n in notes_hi)
    assert np.abs(clamped - at_hi).max() <= 1  # the same expression (video rounding)
    given, notes_x = frames(5, extrapolate=True)
    assert not any("clamped" in n for n in notes_x)
    # the values handed to the renderer: the keyframe's frame at the top (the others hold
    # frame 0's expression)
    for value, extrapolate, want in (("5", False, hi), (f"{hi:.6f}", False, hi),
                                     ("5", True, 5.0)):
        plan = videos.plan_render(RenderOptions(
            toy_run, out=tmp_path / "p.mp4", expressions=[f"jawOpen={value}"], frames=3,
            extrapolate=extrapolate, device="cpu"), log=lambda _: None)
        assert np.isclose(plan.values[:, jaw].max(), want)


@pytest.mark.slow
def test_side_by_side_panels_carry_titles_where_they_fit(toy_run, tmp_path):
    render(RenderOptions(toy_run, out=tmp_path / "v.mp4", expressions=["jawOpen=1"], frames=2,
                         size=80, side_by_side=True, device="cpu"))
    sbs = read_frames(tmp_path / "v_sbs.mp4")[0]
    assert sbs.shape[0] == 80 + 14  # the panels under a strip of titles
    titles = sbs[:14].astype(int)
    assert np.median(titles) > 200 and titles.min() < 100  # black text on white


@pytest.mark.slow
def test_the_capture_carries_the_clips_sound(toy_dataset, toy_run, tmp_path):
    """--split capture of a preprocessed clip (frame times, the source video) at its own
    pace: the video and the side by side carry the clip's sound from the first frame's
    time; another --fps, --no-sound, a source that is gone or a silent sound track: no
    sound, with a note."""
    import json
    import shutil

    from flamenerf.data.video import has_sound, probe_video
    from media import clip_with_sound

    data = tmp_path / "data"
    shutil.copytree(toy_dataset, data)
    meta = json.loads((data / "transforms.json").read_text())
    meta["source"]["video"] = str(clip_with_sound(tmp_path / "clip.mp4", 2.0))
    for f in meta["frames"]:
        if f.get("frame_index") is not None:
            f["time"] = 0.5 + f["frame_index"] / 10  # the clip's frames at 10 fps from 0.5 s
    (data / "transforms.json").write_text(json.dumps(meta))
    notes = []

    def render_to(name, **kw):
        from flamenerf.rendering.videos import render_videos

        render_videos(RenderOptions(toy_run, out=tmp_path / name, split="capture",
                                    dataset=data, device="cpu", **kw), log=notes.append)
        return tmp_path / name

    out = render_to("v.mp4", side_by_side=True)
    assert has_sound(out) and has_sound(tmp_path / "v_sbs.mp4")
    assert abs(probe_video(out).duration - 0.6) < 0.1  # 6 frames at 10 fps
    assert any("with the clip's sound" in n and "from 0.50 s" in n for n in notes)
    assert not has_sound(render_to("fast.mp4", fps=20))
    assert any("no sound: --fps 20 plays the clip at another pace" in n for n in notes)
    assert not has_sound(render_to("quiet.mp4", sound=False))
    (tmp_path / "clip.mp4").unlink()
    assert not has_sound(render_to("gone.mp4"))
    assert any("no sound: the clip" in n and "no longer there" in n for n in notes)
    clip_with_sound(tmp_path / "clip.mp4", 2.0, volume=0.0)  # a muted recording
    assert not has_sound(render_to("muted.mp4"))
    assert any("no sound: the clip's sound track is silent" in n for n in notes)


@pytest.mark.slow
def test_a_gap_in_the_clip_plays_for_its_time(toy_dataset, toy_run, tmp_path):
    """--split capture of a clip with a gap (frames the camera dropped, or where no face was
    found): the frame before it is shown for as long as the gap lasted, so that the video
    keeps the clip's length (and its sound its step), with a note; without a gap every
    frame once."""
    import json
    import shutil

    from flamenerf.data.video import probe_video
    from flamenerf.rendering.videos import render_videos

    data = tmp_path / "data"
    shutil.copytree(toy_dataset, data)
    meta = json.loads((data / "transforms.json").read_text())
    times = [0.5, 0.6, 0.7, 1.1, 1.2, 1.3]  # 10 fps, 0.3 s missing after the third frame
    for f in meta["frames"]:
        if f.get("frame_index") is not None:
            f["time"] = times[f["frame_index"]]
    (data / "transforms.json").write_text(json.dumps(meta))
    notes = []
    out = tmp_path / "v.mp4"
    render_videos(RenderOptions(toy_run, out=out, split="capture", dataset=data,
                                device="cpu", depth=True), log=notes.append)
    frames = read_frames(out)
    assert len(frames) == 9 == probe_video(out).num_frames  # 1 + 1 + 4 + 1 + 1 + 1
    assert len(read_frames(tmp_path / "v_depth.mp4")) == 9
    assert abs(probe_video(out).fps - 10) < 1e-3
    assert np.abs(frames[2].astype(int) - frames[5].astype(int)).max() <= 8  # one frame held
    assert any("1 gap in the clip" in n and "0.40 s" in n for n in notes)
    notes.clear()
    render_videos(RenderOptions(toy_run, out=tmp_path / "f.mp4", split="capture",
                                dataset=data, device="cpu", fps=20), log=notes.append)
    assert len(read_frames(tmp_path / "f.mp4")) == 6  # another pace: every frame once
    assert not any("gap" in n for n in notes)

