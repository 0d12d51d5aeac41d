"""Video decoding with rotation metadata, frame selection, unreadable inputs, and atomic
writing."""

from __future__ import annotations

import numpy as np
import pytest

from flamenerf.data.video import VideoWriter, iter_frames, probe_video, select_frames
from flamenerf.errors import UserError
from media import astronaut_frames, clip_with_sound, hdr_clip, variable_rate_clip


def test_probe_and_decode(astronaut_video):
    assert probe_video(astronaut_video).times is None  # evenly spaced: frame i at i / fps
    info = probe_video(astronaut_video)
    assert (info.width, info.height, info.num_frames) == (256, 256, 12)
    assert info.fps == pytest.approx(10.0) and info.rotation == 0
    frames = list(iter_frames(info, [0, 5, 11]))
    assert [i for i, _ in frames] == [0, 5, 11]
    assert frames[0][1].shape == (256, 256, 3) and frames[0][1].dtype == np.uint8


def test_rotation_metadata_is_honoured(rotated_video):
    info = probe_video(rotated_video)
    assert info.rotation in (90, 270)
    assert (info.width, info.height) == (160, 320)  # stored 320x160, shown portrait
    frames = [f for _, f in iter_frames(info)]
    assert len(frames) == 5 and frames[0].shape == (320, 160, 3)
    # the white band of the stored frame's left edge is now along the top or bottom
    rows = frames[0].mean(axis=(1, 2))
    assert max(rows[:30].mean(), rows[-30:].mean()) > 200
    assert frames[0][:, :30].mean() < 200


def test_select_frames():
    assert select_frames(10, 30.0).tolist() == list(range(10))
    assert select_frames(30, 30.0, fps=10).tolist() == list(range(0, 30, 3))
    assert select_frames(100, 30.0, max_frames=5).tolist() == [0, 25, 50, 74, 99]
    sel = select_frames(300, 30.0, fps=15, max_frames=20)
    assert len(sel) == 20 and sel[0] == 0 and np.all(np.diff(sel) > 0)
    with pytest.raises(UserError, match="--fps"):
        select_frames(10, 30.0, fps=0)


def test_unreadable_inputs(tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        probe_video(tmp_path / "nope.mp4")
    txt = tmp_path / "notes.mp4"
    txt.write_text("hello, this is not a video\n" * 10)
    with pytest.raises(UserError, match="notes.mp4: not a readable video"):
        probe_video(txt)
    junk = tmp_path / "junk.mov"
    junk.write_bytes(bytes(range(256)) * 50)
    with pytest.raises(UserError, match="junk.mov"):
        probe_video(junk)


def test_an_aborted_video_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError):
        with VideoWriter(tmp_path / "a.mp4", fps=10) as v:
            v.write(np.zeros((9, 9, 3)))  # odd sizes are padded
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_a_video_carries_a_clips_sound_cut_to_its_length(tmp_path):
    from flamenerf.data.video import Soundtrack, has_sound

    clip = clip_with_sound(tmp_path / "clip.mp4")
    assert has_sound(clip)
    out = tmp_path / "out.mp4"
    with VideoWriter(out, fps=10, sound=Soundtrack(clip, 1.0)) as v:
        for _ in range(12):  # 1.2 s
            v.write(np.zeros((16, 16, 3), np.uint8))
    assert has_sound(out)
    assert abs(probe_video(out).duration - 1.2) < 0.1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.mp4", "out.mp4"]
    silent = tmp_path / "silent.mp4"  # a source without sound: a warning, a silent video
    with VideoWriter(silent, fps=10, sound=Soundtrack(out.with_name("missing.mp4"), 0)) as v:
        v.write(np.zeros((16, 16, 3), np.uint8))
    assert silent.is_file() and not has_sound(silent)
    assert not any(".tmp." in p.name for p in tmp_path.iterdir())


def test_loudest_tells_a_muted_recording_from_sound(tmp_path):
    from flamenerf.data.video import SILENT_DB, Soundtrack, loudest

    tone = loudest(Soundtrack(clip_with_sound(tmp_path / "tone.mp4", 1.0), 0.2), 0.5)
    muted = loudest(Soundtrack(clip_with_sound(tmp_path / "muted.mp4", 1.0, 0.0), 0.0), 1.0)
    assert tone > -20 and muted < SILENT_DB
    # a file without a sound track, or none at all: ffmpeg cannot tell
    assert loudest(Soundtrack(tmp_path / "missing.mp4", 0.0), 1.0) is None


def test_a_variable_rate_clip_decodes_its_own_frames(tmp_path):
    """A clip that dropped frames (a gap of half a second, its nominal rate kept): each
    decoded frame is the stream's own, as many as `probe_video` counts, none repeated (a
    constant-rate decode filled the gap with 15 copies and cut as many from the end)."""
    info = probe_video(variable_rate_clip(tmp_path / "vfr.mp4"))
    assert info.num_frames == 20
    got = list(iter_frames(info))
    assert [i for i, _ in got] == list(range(20))
    greys = [float(img.mean()) for _, img in got]
    assert np.allclose(greys, [10 * k for k in range(20)], atol=2)
    # their own times: 30 fps, then half a second without a frame; evenly spaced frames
    # (every other video here) keep i / fps
    assert info.times is not None
    assert np.allclose(np.diff(info.times), [1 / 30] * 9 + [0.5 + 1 / 30] + [1 / 30] * 9,
                       atol=1e-3)
    assert info.frame_time(10) == pytest.approx(25 / 30, abs=1e-3)
    # --fps by those times: the frame nearest each tick of 10 a second (by index, at the
    # clip's average rate, it took ~17 a second wherever the clip has frames)
    sel = select_frames(info.num_frames, info.fps, 10, None, info.times)
    assert sel.tolist() == [0, 3, 6, 9, 10, 12, 15, 18]
    # the selection by index picks those frames too
    assert [round(float(img.mean()) / 10) for _, img in iter_frames(info, np.array([3, 12, 19]))] \
        == [3, 12, 19]


@pytest.mark.parametrize("transfer", ["arib-std-b67", "smpte2084"])
def test_an_hdr_clip_decodes_to_sdr(tmp_path, transfer):
    """A phone's HDR video (HLG or PQ, BT.2020, 10 bits) of an SDR picture at the reference
    white decodes close to that picture; taken as stored it came out dim and pale."""
    src = np.stack(astronaut_frames(3, 64))
    info = probe_video(hdr_clip(tmp_path / "hdr.mp4", transfer, src))
    assert info.hdr == transfer and info.num_frames == 3
    got = np.stack([img for _, img in iter_frames(info)]).astype(np.float64)
    assert np.abs(got - src).mean() < 9
    info.hdr = None  # as stored
    raw = np.stack([img for _, img in iter_frames(info)]).astype(np.float64)
    assert np.abs(raw - src).mean() > 18


def test_an_ffmpeg_failure_is_one_line(tmp_path, monkeypatch):
    """ffmpeg's whole log came through in the error; now its line that says what failed
    (here an ffmpeg without the HDR filters)."""
    from flamenerf.data import video

    info = probe_video(hdr_clip(tmp_path / "hdr.mp4", "arib-std-b67",
                                np.stack(astronaut_frames(2, 32))))
    monkeypatch.setattr(video, "SDR_FILTER", "nosuchfilter")
    with pytest.raises(UserError) as e:
        list(iter_frames(info))
    msg = str(e.value)
    assert "\n" not in msg and "hdr.mp4" in msg and "nosuchfilter" in msg
    assert "tone-map" in msg
