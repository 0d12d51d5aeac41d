"""Sound under a render and frames without the codec's loss: a drive carries its video's
sound in step with its frames (a click track, a gap without a face), `--audio` lays any
sound file under any render, `--frames-dir` writes the frames as PNGs with the sound as a
wav; and a control the training frames never move is named before a render asks for it."""

from __future__ import annotations

import json
import subprocess

import imageio.v3 as iio
import numpy as np
import pytest
from media import astronaut_frames

from flamenerf.cli import main
from flamenerf.data.expression_range import ExpressionRange
from flamenerf.data.video import _ffmpeg, read_frames, sound_duration, video_packets, write_video
from flamenerf.rendering.soundtrack import drive_pace, in_step

RATE = 16_000


def pcm(path) -> np.ndarray:
    """A file's first sound track as mono float samples at RATE."""
    r = subprocess.run([_ffmpeg(), "-v", "error", "-i", str(path), "-map", "0:a:0", "-f",
                        "f32le", "-ac", "1", "-ar", str(RATE), "-"], capture_output=True,
                       check=True)
    return np.frombuffer(r.stdout, np.float32)


def with_sound(video, samples: np.ndarray, out):
    raw = out.with_suffix(".raw")
    raw.write_bytes(samples.astype(np.float32).tobytes())
    subprocess.run([_ffmpeg(), "-v", "error", "-y", "-i", str(video), "-f", "f32le", "-ar",
                    str(RATE), "-ac", "1", "-i", str(raw), "-map", "0:v", "-map", "1:a",
                    "-c:v", "copy", "-c:a", "aac", str(out)], check=True)
    return out


def tone(path, seconds: float):
    subprocess.run([_ffmpeg(), "-v", "error", "-y", "-f", "lavfi", "-i",
                    f"sine=frequency=440:duration={seconds}", str(path)], check=True)
    return path


@pytest.fixture(scope="module")
def click_drive(tmp_path_factory):
    """A 2 s driving video at 10 fps whose frames 10-13 show no face, with a click at
    1.5 s (during frame 15)."""
    root = tmp_path_factory.mktemp("drive")
    frames = astronaut_frames(20, 128)
    for i in range(10, 14):
        frames[i] = np.full_like(frames[i], 128)
    write_video(root / "silent.mp4", frames, fps=10)
    a = np.zeros(2 * RATE, np.float32)
    a[int(1.5 * RATE):int(1.5 * RATE) + 160] = 0.8
    return with_sound(root / "silent.mp4", a, root / "drive.mp4")


def run_cli(capsys, *args):
    rc = main([str(a) for a in args])
    out = capsys.readouterr()
    return rc, out.out, out.err


@pytest.mark.slow
def test_a_drive_carries_its_sound_in_step_with_its_frames(toy_run, click_drive, tmp_path,
                                                           capsys):
    out = tmp_path / "d.mp4"
    rc, log, err = run_cli(capsys, "render", toy_run, "--drive", click_drive, "--out", out,
                           "--side-by-side", "--threads", "1")
    assert rc == 0, err
    assert "with the driving video's sound" in log
    for video in (out, tmp_path / "d_sbs.mp4"):
        # 16 tracked frames; the last before the gap held for its 0.5 s: 20 at 10 fps
        assert video_packets(video) == 20
        assert abs(sound_duration(video) - 2.0) < 0.05
        click = np.abs(pcm(video)).argmax() / RATE
        assert abs(click - 1.5) < 0.1, click  # within one frame of where it was


@pytest.mark.slow
def test_a_drive_without_sound_or_with_no_sound_gives_a_silent_video(toy_run, click_drive,
                                                                     tmp_path, capsys):
    out = tmp_path / "n.mp4"
    rc, log, err = run_cli(capsys, "render", toy_run, "--drive", click_drive, "--out", out,
                           "--no-sound", "--threads", "1")
    assert rc == 0, err
    assert sound_duration(out) is None and "driving video's sound" not in log
    assert video_packets(out) == 20  # its timing kept all the same


def test_drive_pace_holds_the_frame_before_a_gap():
    times = np.array([0.0, 0.1, 0.2, 0.7, 0.8])
    shown = drive_pace(times, 10.0)
    assert shown.tolist() == [1, 1, 5, 1, 1]
    assert in_step(times, shown, 10.0)
    assert not in_step(times, None, 10.0)  # the gap played as one frame: out of step
    assert drive_pace(np.arange(5) / 10, 10.0) is None


@pytest.mark.slow
@pytest.mark.parametrize("seconds, word", [(0.5, "padded with silence"), (3.0, "cut to")])
def test_audio_is_laid_under_any_render_cut_or_padded(seconds, word, toy_run, tmp_path,
                                                      capsys):
    out = tmp_path / "a.mp4"
    rc, log, err = run_cli(capsys, "render", toy_run, "--frames", "30", "--fps", "30",
                           "--audio", tone(tmp_path / "t.wav", seconds), "--out", out,
                           "--threads", "1")
    assert rc == 0, err
    assert word in log
    assert video_packets(out) == 30 and abs(sound_duration(out) - 1.0) < 0.05
    heard = np.abs(pcm(out))
    assert heard[: RATE // 4].max() > 0.1  # the tone from its start
    if seconds < 1:
        assert heard[int(0.75 * RATE):].max() < 0.01  # then silence


@pytest.mark.parametrize("make, args, words", [
    (None, [], ["nothere.wav", "does not exist"]),
    ("text", [], ["notes.wav", "no sound"]),
    ("tone", ["--no-sound"], ["--audio", "--no-sound"]),
])
def test_audio_errors_are_one_line_before_rendering(make, args, words, toy_run, tmp_path,
                                                    capsys):
    path = tmp_path / ("nothere.wav" if make is None else "notes.wav")
    if make == "text":
        path.write_text("not a sound")
    elif make == "tone":
        tone(path, 0.5)
    rc, log, err = run_cli(capsys, "render", toy_run, "--audio", path, "--out",
                           tmp_path / "x.mp4", *args)
    assert rc == 2
    line = [ln for ln in err.splitlines() if ln.startswith("flamenerf: error:")]
    assert len(line) == 1 and "Traceback" not in err
    for w in words:
        assert w in line[0]
    assert not (tmp_path / "x.mp4").exists()


@pytest.mark.slow
def test_frames_dir_writes_the_frames_and_the_sound_without_loss(toy_run, tmp_path, capsys):
    out, frames = tmp_path / "f.mp4", tmp_path / "frames"
    args = ["render", toy_run, "--expressions", "jawOpen=0.9", "--frames", "6", "--fps", "10",
            "--audio", tone(tmp_path / "t.wav", 2.0), "--out", out, "--frames-dir", frames,
            "--threads", "1"]
    rc, log, err = run_cli(capsys, *args)
    assert rc == 0, err
    assert str(frames) in log
    meta = json.loads((frames / "frames.json").read_text())
    assert meta["frames"] == 6 and meta["fps"] == 10 and meta["sound"] == "sound.wav"
    pngs = sorted(frames.glob("*.png"))
    assert [p.name for p in pngs] == [f"{i:06d}.png" for i in range(6)]
    assert abs(sound_duration(frames / "sound.wav") - 0.6) < 0.02
    video = read_frames(out)
    for png, v in zip(pngs, video):  # the same pictures, the PNGs without the codec's loss
        img = iio.imread(png)
        assert img.shape == v.shape and np.abs(img.astype(int) - v).mean() < 12
    rc, _, err = run_cli(capsys, *args, "--overwrite")  # the mp4 and the folder replaced
    assert rc == 0, err
    rc, _, err = run_cli(capsys, *args[:-4], "--out", tmp_path / "g.mp4", "--frames-dir",
                         frames)
    assert rc == 2 and "earlier render" in err  # not replaced without --overwrite
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    rc, _, err = run_cli(capsys, *args[:-4], "--out", tmp_path / "h.mp4", "--frames-dir",
                         tmp_path / "mine", "--overwrite")
    assert rc == 2 and "holds other files" in err
    assert (tmp_path / "mine" / "notes.txt").read_text() == "mine"
    assert not [p for p in tmp_path.iterdir() if ".flamenerf-" in p.name]


def test_controls_the_training_frames_never_move_are_named():
    rng = ExpressionRange.of(["jawOpen", "eyeBlinkLeft"], np.array([[0.0, 0.0], [0.8, 0.05]]))
    assert rng.uncovered(np.array([[0.5, 0.9]])) == ["eyeBlinkLeft"]
    assert rng.uncovered(np.array([[0.9, 0.1]])) == []  # within reach of the clip's range
    assert rng.uncovered(None, controls=[1]) == ["eyeBlinkLeft"]  # an edit of it
    assert rng.uncovered(None, controls=[0]) == []
    assert "never move eyeBlinkLeft" in ExpressionRange.not_covered_note(["eyeBlinkLeft"],
                                                                         "the drive")


def test_the_side_by_side_caption_says_what_the_clip_cannot_give():
    from flamenerf.rendering.videos import caption_strip, lacking_caption, short_names

    assert short_names(["eyeBlinkLeft", "eyeBlinkRight", "jawOpen", "browDownLeft"]) == \
        "eyeBlink L/R, jawOpen, browDownLeft"
    assert lacking_caption([], []) is None
    cap = lacking_caption(["mouthSmileLeft"], ["eyeBlinkLeft", "eyeBlinkRight"])
    assert cap == "never in the clip: mouthSmileLeft; generic shape: eyeBlink L/R"
    wide, narrow = caption_strip(cap, 400), caption_strip(cap, 120)
    assert wide.shape == (14, 400, 3) and narrow.shape == (14, 120, 3)
    assert wide.min() < 0.5  # text drawn
