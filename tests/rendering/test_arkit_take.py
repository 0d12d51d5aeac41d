"""ARKit takes as Live Link Face exports them (`--expressions take.csv`, `--head-pose take`,
the viewer's --track): read from a synthetic take this file writes, not a recording."""

from __future__ import annotations

import math

import numpy as np
import pytest

from flamenerf.errors import UserError
from flamenerf.rendering.expressions import from_items, load_file, source_head_pose
from flamenerf.rendering.takes import frame_rate, timecode_rate

# Live Link Face's 52 blendshape columns, in its order
BLENDSHAPES = (
    "EyeBlinkLeft,EyeLookDownLeft,EyeLookInLeft,EyeLookOutLeft,EyeLookUpLeft,EyeSquintLeft,"
    "EyeWideLeft,EyeBlinkRight,EyeLookDownRight,EyeLookInRight,EyeLookOutRight,EyeLookUpRight,"
    "EyeSquintRight,EyeWideRight,JawForward,JawRight,JawLeft,JawOpen,MouthClose,MouthFunnel,"
    "MouthPucker,MouthRight,MouthLeft,MouthSmileLeft,MouthSmileRight,MouthFrownLeft,"
    "MouthFrownRight,MouthDimpleLeft,MouthDimpleRight,MouthStretchLeft,MouthStretchRight,"
    "MouthRollLower,MouthRollUpper,MouthShrugLower,MouthShrugUpper,MouthPressLeft,"
    "MouthPressRight,MouthLowerDownLeft,MouthLowerDownRight,MouthUpperUpLeft,MouthUpperUpRight,"
    "BrowDownLeft,BrowDownRight,BrowInnerUp,BrowOuterUpLeft,BrowOuterUpRight,CheekPuff,"
    "CheekSquintLeft,CheekSquintRight,NoseSneerLeft,NoseSneerRight,TongueOut").split(",")
HEAD = ["HeadYaw", "HeadPitch", "HeadRoll"]
EYES = [f"{e}Eye{a}" for e in ("Left", "Right") for a in ("Yaw", "Pitch", "Roll")]
TOY_NAMES = ["jawOpen", "mouthSmileLeft", "browInnerUp"]  # tests/toy.py's controls
START = 12 * 3600 + 27 * 60 + 47  # 12:27:47:00.000


def sample(t: float, seconds: float) -> dict[str, float]:
    """The sample take at `t` s: the jaw opens and closes, a blink at mid-take, the head
    turns (radians, as Live Link Face stores it) and nods a little."""
    u = t / seconds
    blink = math.exp(-(((t - seconds / 2) / 0.06) ** 2))
    return {"JawOpen": 0.5 * (1 - math.cos(2 * math.pi * u)), "EyeBlinkLeft": blink,
            "EyeBlinkRight": blink, "BrowInnerUp": 0.2 * u, "HeadYaw": 0.3 * math.sin(math.pi * u),
            "HeadPitch": 0.1 * u, "HeadRoll": 0.0}


def timecode(seconds: float, rate: int) -> str:
    """`HH:MM:SS:FF.mmm` of a time at a timecode `rate` (.mmm: the fraction of a frame)."""
    frames = round(seconds * rate, 6)
    whole, frac = int(frames), frames - int(frames)
    s, ff = divmod(whole, rate)
    return f"{s // 3600:02d}:{s // 60 % 60:02d}:{s % 60:02d}:{ff:02d}.{round(frac * 1000):03d}"


def write_take(path, seconds: float = 2.0, fps: float = 60, rate: int = 30, head: bool = True,
               start: float = START):
    """A Live Link Face take of `seconds` with rows at `fps` and timecodes at `rate` (the
    app's 60 fps tracking under a 30 fps timecode: FF 0-29, .000 and .500)."""
    cols = ["Timecode", "BlendShapeCount", *BLENDSHAPES, *(HEAD if head else []), *EYES]
    lines = [",".join(cols)]
    for i in range(int(round(seconds * fps))):
        v = sample(i / fps, seconds)
        lines.append(",".join([timecode(start + i / fps, rate), "61"]
                              + [f"{v.get(c, 0.0):.10f}" for c in cols[2:]]))
    path.write_text("\n".join(lines) + "\n")
    return path


def test_a_take_plays_at_its_rows_rate_with_its_names_and_values(tmp_path):
    take = write_take(tmp_path / "take.csv")
    lines = take.read_text().splitlines()
    assert lines[1].startswith("12:27:47:00.000,61,") and lines[2].startswith("12:27:47:00.500")
    seq = load_file(take, TOY_NAMES)
    assert seq.fps == 60 and len(seq) == 120 and seq.take == take
    t = np.arange(120) / 60
    want = np.array([[sample(x, 2.0)[c] for c in ("JawOpen", "BrowInnerUp")] for x in t])
    np.testing.assert_allclose(seq.values[:, [0, 2]], want, atol=1e-5)
    assert not seq.values[:, 1].any()  # mouthSmileLeft: 0 in the take
    # the blendshapes the run lacks, noted; BlendShapeCount, head and eye angles are not controls
    note = next(n for n in seq.notes if "ignored blendshapes" in n)
    assert "eyeBlinkLeft" in note and "Head" not in note and "BlendShapeCount" not in note


def test_head_angles_are_radians_turned_into_the_heads_degrees(tmp_path):
    seq = load_file(write_take(tmp_path / "take.csv"), TOY_NAMES)
    head = seq.head_pose
    assert head.shape == (120, 6) and not head[0].any() and not head[:, 3:].any()
    # HeadYaw > 0 turns to the subject's right (yaw < 0 here), HeadPitch > 0 lowers the
    # chin (pitch < 0): 0.3 rad = 17.2 degrees at mid-take
    assert head[60, 0] == pytest.approx(-math.degrees(0.3), abs=0.6)
    assert head[60, 1] == pytest.approx(-math.degrees(0.05), abs=0.6)
    assert abs(head[:, 2]).max() < 1.0
    assert source_head_pose("take", seq)[60, 0] == pytest.approx(head[60, 0])


def test_resampled_to_the_asked_rate_and_timecode_rates(tmp_path):
    take = write_take(tmp_path / "take.csv")
    seq = from_items([str(take)], TOY_NAMES, np.zeros(3), None, fps=25)
    assert seq.fps == 25 and len(seq) == 50  # 119/60 s at 25 fps, to the nearest frame
    t = np.arange(50) / 25
    np.testing.assert_allclose(seq.values[:, 0], [sample(x, 2.0)["JawOpen"] for x in t],
                               atol=2e-3)
    assert len(seq.head_pose) == 50
    # rows every other frame of a 60 fps timecode (FF 0-58 in steps of 2): 30 fps rows
    seq = load_file(write_take(tmp_path / "t60.csv", fps=30, rate=60), TOY_NAMES)
    assert seq.fps == 30 and len(seq) == 60 and not seq.notes[1:]
    assert timecode_rate([(1, 2, 3, ff, 0.0) for ff in (22, 23)] + [(1, 2, 4, 0, 0.0)])[0] == 24
    # within one second, the rate is a guess, said; beyond 60, its largest frame + 1
    rate, note = timecode_rate([(1, 2, 3, ff, 0.0) for ff in range(10)])
    assert rate == 24 and "within one second" in note
    assert timecode_rate([(1, 2, 3, 99, 0.0), (1, 2, 4, 0, 0.0)]) == (100, pytest.approx(
        "timecode frames up to 99, beyond a 60 fps timecode: taken as 100 fps"))
    # the phone's clock a little off 30 fps: snapped to 30
    assert frame_rate(np.arange(10) / 30.0075) == 30 and frame_rate(np.zeros(1)) is None


def test_frames_without_a_face_are_bridged(tmp_path):
    take = write_take(tmp_path / "take.csv", seconds=0.5)
    lines = take.read_text().splitlines()
    row = lines[10].split(",")
    lines[10] = ",".join([row[0], "0"] + ["0"] * (len(row) - 2))  # no face in this frame
    take.write_text("\n".join(lines) + "\n")
    seq = load_file(take, TOY_NAMES)
    assert len(seq) == 30 and any("1 rows without a face" in n for n in seq.notes)
    # row 10 is frame 9: between its neighbours
    assert seq.values[9, 0] == pytest.approx((seq.values[8, 0] + seq.values[10, 0]) / 2)
    assert seq.values[9, 0] == pytest.approx(sample(9 / 60, 0.5)["JawOpen"], abs=1e-2)


@pytest.mark.parametrize("edit, message", [
    (lambda r: r.replace("12:27:47:03.000", "12:27:47-03"), "row 8: timecode '12:27:47-03' is "
     "not HH:MM:SS:FF.mmm"),
    (lambda r: r.replace(",61,", ",61,abc,", 1).rsplit(",", 1)[0] if r.startswith(
        "12:27:47:03.000") else r, "row 8: EyeBlinkLeft is not a number ('abc')"),
    (lambda r: r.rsplit(",", 1)[0] if r.startswith("12:27:47:03.000") else r,
     "row 8 has 62 values, the header names 63"),
    (lambda r: r.replace("12:27:47:03.000", "12:27:47:01.000"), "row 8: timecode "
     "12:27:47:01.000 does not come after row 7's (12:27:47:02.500)"),
])
def test_bad_takes_are_one_line_naming_the_file_and_row(tmp_path, edit, message):
    take = write_take(tmp_path / "take.csv", seconds=0.5)
    lines = take.read_text().splitlines()
    take.write_text("\n".join([lines[0]] + [edit(r) for r in lines[1:]]) + "\n")
    with pytest.raises(UserError) as e:
        load_file(take, TOY_NAMES)
    assert str(e.value) == f"{take}: {message}"


def test_head_pose_take_needs_a_take_with_head_columns(tmp_path):
    seq = load_file(write_take(tmp_path / "nohead.csv", seconds=0.2, head=False), TOY_NAMES)
    assert seq.head_pose is None
    with pytest.raises(UserError, match=r"^--head-pose take: .*nohead\.csv has no HeadYaw, "
                                        r"HeadPitch, HeadRoll columns$"):
        source_head_pose("take", seq)
    with pytest.raises(UserError, match="give one with --expressions take.csv"):
        source_head_pose("take", from_items(["jawOpen=1"], TOY_NAMES, np.zeros(3), 4))
    # each word its own source: a take's head is not a drive's
    with pytest.raises(UserError, match=r"--drive \(a take's: --head-pose take\)"):
        source_head_pose("drive", load_file(write_take(tmp_path / "t.csv", 0.2), TOY_NAMES))


@pytest.mark.slow
def test_render_plays_a_take_at_its_rate(toy_run, tmp_path, capsys):
    from flamenerf.cli import main
    from flamenerf.data.video import probe_video, read_frames

    # across a change of second, as any take longer than one is: its timecode's rate known
    take = write_take(tmp_path / "take.csv", seconds=0.5, start=START + 0.75)
    out = tmp_path / "take.mp4"
    assert main(["render", str(toy_run), "--expressions", str(take), "--out", str(out),
                 "--device", "cpu"]) == 0
    assert len(read_frames(out)) == 30 and probe_video(out).fps == pytest.approx(60)
    said = capsys.readouterr().out
    assert "ignored blendshapes this run lacks" in said and "within one second" not in said
    # at another rate: resampled, as long
    out = tmp_path / "take25.mp4"
    assert main(["render", str(toy_run), "--expressions", str(take), "--out", str(out),
                 "--fps", "25", "--device", "cpu"]) == 0
    assert len(read_frames(out)) == 12 and probe_video(out).fps == pytest.approx(25)


@pytest.mark.slow
def test_head_pose_take_turns_a_head_run(head_run, tmp_path):
    from flamenerf.rendering.videos import RenderOptions, head_transforms
    from flamenerf.training.run import load_run

    run = load_run(head_run, "cpu")
    ds = run.dataset(None)
    take = write_take(tmp_path / "take.csv", seconds=0.5)
    seq = load_file(take, run.expression_names)
    assert seq.values[:, run.expression_names.index("eyeBlinkLeft")].max() > 0.5
    opts = RenderOptions(head_run, expressions=[str(take)], head_pose=["take"])
    T = head_transforms(opts, run, ds, len(seq), seq=seq)
    assert T.shape == (30, 4, 4) and np.allclose(T[0], np.eye(4), atol=1e-6)
    assert not np.allclose(T[-1], np.eye(4), atol=1e-3)  # turned by the take's head


def test_the_viewer_plays_a_take_as_a_track(tmp_path):
    from flamenerf.viewer.tracks import load_track_file

    take = write_take(tmp_path / "take.csv")
    track = load_track_file(take, TOY_NAMES)
    assert track.fps == 60 and track.num_frames == 120 and track.duration() == 2.0
    assert track.render_args == ("--expressions", str(take)) and "take" in track.name
