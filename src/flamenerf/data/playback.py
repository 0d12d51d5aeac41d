"""How a clip's frames play in the time they took: at the rate of its steady steps, with the
frame before a gap (frames the camera dropped, or where no face was found) held for the
gap's time, so that a video of it keeps the clip's length and its sound stays in step.

The frames' times are the `time` that `preprocess` stores with each frame. This module reads
frames only for that field (`Timed`) and so needs nothing of data/dataset.py, which asks it
for a clip's rate (`Dataset.frame_rate`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol

import numpy as np

from flamenerf.data.video import FPS_RANGE

GAP = 1.75
"""A step between consecutive frames longer than this many times the clip's median step
is a gap (frames the camera dropped, or where no face was found): it plays for its time."""


class Timed(Protocol):
    """A frame as far as its timing goes (data/dataset.Frame is one): its fields beyond the
    format's, among them `time`."""

    extra: dict[str, Any]


def playback(times: np.ndarray, rate: float | None = None
             ) -> tuple[float, np.ndarray] | None:
    """How frames at `times` (n,) seconds, increasing, play in the time they took: -> (rate
    in frames per second, the number of times each frame is shown (n,) int >= 1), or None
    (fewer than two frames, or no time between them). The rate (unless given) is that of
    the steps that are no gap (frames spread a little unevenly play evenly, as they were
    filmed); the frame before a gap is shown again for as long as the gap lasted, so that
    the clip keeps its length and its sound stays in step throughout."""
    t = np.asarray(times, np.float64)
    if len(t) < 2 or t[-1] <= t[0]:
        return None

    dt = np.diff(t)
    gap = dt > GAP * np.median(dt)
    steady = dt[~gap]
    if rate is None:
        rate = (len(steady) / steady.sum() if len(steady) and steady.sum() > 0
                else (len(t) - 1) / (t[-1] - t[0]))
        # to a thousandth (times are stored to a microsecond), and within what a video can
        # be written at (a few frames spread over a long clip)
        rate = round(float(np.clip(rate, *FPS_RANGE)), 3)
    shown = np.ones(len(t), np.int64)
    shown[:-1][gap] = np.maximum(1, np.round(dt[gap] * rate)).astype(np.int64)
    return rate, shown


def frame_times(frames: Sequence[Timed]) -> np.ndarray | None:
    """(n,) the frames' `time`s in seconds (`preprocess` stores them), or None where a frame
    has none (the built-in scene's)."""
    times = [f.extra.get("time") for f in frames]
    if times and all(isinstance(t, (int, float)) for t in times):
        return np.asarray(times, np.float64)
    return None


def frames_shown(frames: Sequence[Timed], fps: float) -> np.ndarray | None:
    """(n,) how many ticks of 1 / `fps` each of a clip's `frames` (in order) stays on screen
    as they play in the time they took (`playback`: the frame before a gap held for the
    gap's time); None where each is shown once (no gap, or no times stored)."""
    times = frame_times(frames)
    plan = None if times is None else playback(times, fps)
    return None if plan is None or (plan[1] == 1).all() else plan[1]


def frame_rate(frames: Sequence[Timed]) -> float | None:
    """Frames per second of frames in clip order (`playback`'s rate: that of the steps that
    are no gap); None where a frame stores no time (the built-in scene's)."""
    times = frame_times(frames)
    plan = None if times is None else playback(times)
    return None if plan is None else plan[0]
