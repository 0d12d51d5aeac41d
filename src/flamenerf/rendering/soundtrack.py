"""The sound a render carries, and the pace that keeps its picture in step with it: the
filmed clip's (`--split capture` at the clip's own pace), a driving video's (`--drive`), or
any sound file laid under any render (`--audio`).

A picture keeps step with its source's sound when frame i is on screen at the time it had
in the source (from the first frame's): frames are sampled at the video's rate, and the
frame before a gap (frames the camera dropped, or where no face was found) stays for as
long as the gap lasted (`data/playback.playback`). Where that cannot hold (`--max-frames`
spreading a few frames over the clip, another `--fps` than the clip's) the sound is left
out with a note, not cut short or stretched.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flamenerf.data.dataset import CAPTURE, Dataset
from flamenerf.data.playback import frame_times, frames_shown, playback
from flamenerf.data.video import (SILENT_DB, Soundtrack, has_sound, loudest, sound_duration)
from flamenerf.errors import UserError


def shown_duration(n: int, shown: np.ndarray | None, fps: float) -> float:
    """Seconds a video of `n` frames lasts at `fps`, each frame shown `shown` times."""
    return (n if shown is None else int(np.sum(shown))) / fps


def in_step(times: np.ndarray, shown: np.ndarray | None, fps: float) -> bool:
    """Whether frames from their source at `times` (n,) seconds, played at `fps` and each
    shown `shown` times, are each on screen within one frame of their source time."""
    t = np.asarray(times, np.float64) - times[0]
    ticks = np.ones(len(t)) if shown is None else np.asarray(shown, np.float64)
    starts = np.concatenate([[0.0], np.cumsum(ticks)[:-1]]) / fps
    return bool(np.abs(starts - t).max() <= 1.0 / fps + 1e-6)


def drive_pace(times: np.ndarray | None, fps: float) -> np.ndarray | None:
    """(n,) how many ticks of 1 / `fps` each driving frame (at `times` in its video) stays:
    the frame before a gap (no face found there) for the gap's time, so that the drive
    keeps its video's timing; None where each is shown once (or no times)."""
    if times is None:
        return None
    plan = playback(np.asarray(times, np.float64), fps)
    return None if plan is None or (plan[1] == 1).all() else plan[1]


def audible(sound: Soundtrack, duration: float, what: str, log) -> Soundtrack | None:
    """`sound`, or None with a note where its first `duration` seconds are silence (a
    phone's muted recording reads about -90 dB)."""
    peak = loudest(sound, duration)
    if peak is not None and peak < SILENT_DB:
        log(f"note: no sound: {what} is silent (its loudest {peak:g} dB)")
        return None
    return sound


def clip_sound(opts, ds: Dataset, frames: list, fps: float, log=print,
               shown: np.ndarray | None = None) -> Soundtrack | None:
    """The clip's sound for a render of its capture `frames` in order at `fps` (each shown
    `shown` times: `clip_pace`), or None: only the whole capture's frames (or its first
    ones, with --max-frames) at the clip's own pace keep step with it; a note where the
    sound was wanted but cannot come or is silence."""
    times = frame_times(frames)
    if not opts.sound or opts.split != CAPTURE or times is None:
        return None  # the built-in scene's frames store no times: it has no sound
    src = ds.source.get("video") if isinstance(ds.source, dict) else None
    rate = ds.frame_rate()
    if rate is not None and abs(fps - rate) > 1e-3:
        log(f"note: no sound: --fps {fps:g} plays the clip at another pace than its own "
            f"({rate:g} fps)")
        return None
    if not isinstance(src, str) or not Path(src).is_file():
        log(f"note: no sound: the clip {src} is no longer there (--no-sound hides this)")
        return None
    if not has_sound(src):
        return None
    sound = audible(Soundtrack(Path(src), float(times[0])),
                    shown_duration(len(frames), shown, fps), "the clip's sound track", log)
    if sound is not None:
        log(f"note: with the clip's sound ({src}, from {times[0]:.2f} s; --no-sound leaves "
            "it out)")
    return sound


def clip_pace(opts, ds: Dataset, frames: list, fps: float, log=print) -> np.ndarray | None:
    """How many times each of the capture's `frames` is shown when they play at the clip's
    own pace (`data/playback.playback`): the frame before a gap (frames the camera dropped, or
    where no face was found) again for as long as the gap lasted, so that the video keeps
    the clip's timing; None where every frame is shown once (no gap, another split, or
    another pace)."""
    rate = ds.frame_rate()
    if opts.split != CAPTURE or rate is None or abs(fps - rate) > 1e-3:
        return None
    shown = frames_shown(frames, fps)
    if shown is None:
        return None
    gaps = int((shown > 1).sum())
    log(f"note: {gaps} gap{'s' if gaps > 1 else ''} in the clip (frames the camera dropped "
        f"or without a face; the longest {shown.max() / fps:.2f} s): the frame before "
        f"{'each' if gaps > 1 else 'it'} is shown for as long, so that the video keeps the "
        "clip's timing")
    return shown


def drive_sound(opts, times: np.ndarray | None, shown: np.ndarray | None, fps: float,
                log=print) -> Soundtrack | None:
    """The driving video's sound for its tracked frames at `times` (n,) played at `fps`
    (each shown `shown` times: `drive_pace`), or None: where the video has none, it is
    silence, or the frames do not keep step with it (a note says why)."""
    if not opts.sound or not opts.drive or times is None or not has_sound(opts.drive):
        return None
    if not in_step(times, shown, fps):
        why = ("--max-frames spreads the frames over the clip" if opts.max_frames is not None
               else f"--fps {fps:g} plays its frames at another pace than they were taken")
        log(f"note: no sound: {why}, so the video does not keep step with the driving "
            "video's sound (--audio FILE lays a sound under it anyway)")
        return None
    sound = audible(Soundtrack(Path(opts.drive), float(times[0])),
                    shown_duration(len(times), shown, fps), "the driving video's sound", log)
    if sound is not None:
        log(f"note: with the driving video's sound (from {times[0]:.2f} s; --no-sound leaves "
            "it out)")
    return sound


def check_audio(path: Path) -> float:
    """A sound file for --audio (wav, mp3, m4a, or a video with sound): its duration in
    seconds, else a one-line UserError naming it."""
    if path.is_dir():
        raise UserError(f"{path}: is a folder; give --audio a sound file")
    if not path.is_file():
        raise UserError(f"{path}: sound file does not exist")
    seconds = sound_duration(path)
    if seconds is None:
        raise UserError(f"{path}: has no sound that ffmpeg can read (give a wav, mp3 or m4a "
                        "file, or a video with sound)")
    return seconds


def audio_sound(path: Path, duration: float, log=print) -> Soundtrack:
    """The sound file `path` laid under a render of `duration` seconds from its start,
    trimmed or padded with silence to that length (a note says which)."""
    seconds = check_audio(path)
    if seconds > duration + 0.05:
        log(f"note: with the sound of {path}, cut to the video's {duration:.2f} s (it lasts "
            f"{seconds:.2f} s)")
    elif seconds < duration - 0.05:
        log(f"note: with the sound of {path}, padded with silence to the video's "
            f"{duration:.2f} s (it lasts {seconds:.2f} s)")
    else:
        log(f"note: with the sound of {path}")
    return Soundtrack(path, 0.0)
