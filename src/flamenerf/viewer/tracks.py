"""Expression tracks the viewer can play: the dataset's own sequences, a tour of its controls,
`flamenerf track` output files and ARKit takes (Live Link Face CSV), each mapped onto the
run's expression controls."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flamenerf.data.dataset import Dataset, Frame
from flamenerf.data.playback import frames_shown
from flamenerf.data.expression_range import training_expressions
from flamenerf.errors import UserError
from flamenerf.rendering.expressions import from_items, load_take, map_by_name, split_fps
from flamenerf.rendering.takes import is_take
from flamenerf.tracking.expressions import load_expressions


@dataclass
class Track:
    name: str
    frames: np.ndarray  # (T, E) float32, in the run's expression order
    fps: float
    clip: list[Frame] | None = None  # the dataset's frames it plays, if it is theirs
    render_args: tuple[str, ...] = ()  # `flamenerf render`'s options for the same source
    shown: np.ndarray | None = None
    """(T,) int: ticks of 1 / fps each frame stays (a clip's gaps held, as `render` holds
    them: data/playback.playback); None: one each."""

    @property
    def num_frames(self) -> int:
        return int(self.frames.shape[0])

    def duration(self) -> float:
        return (self.num_frames if self.shown is None else int(self.shown.sum())) / self.fps

    def frame_at(self, start: int, seconds: float, loop: bool) -> tuple[int, bool]:
        """The frame shown `seconds` into playing from frame `start` -> (frame, whether the
        track ran out: without `loop` its last frame, which stays)."""
        ends = (np.arange(1, self.num_frames + 1) if self.shown is None
                else np.cumsum(self.shown))  # the tick each frame gives way at
        tick = (ends[start - 1] if start > 0 else 0) + int(seconds * self.fps)
        if tick >= ends[-1]:
            if not loop:
                return self.num_frames - 1, True
            tick %= int(ends[-1])
        return int(np.searchsorted(ends, tick, side="right")), False


def dataset_tracks(ds: Dataset) -> list[Track]:
    """`capture`: every frame of the video in order (train + val); then each split."""
    out: list[Track] = []
    capture = ds.capture()
    fps = ds.frame_rate() or 30.0
    if capture:
        out.append(Track(f"capture ({len(capture)} frames)", ds.expression_matrix(capture), fps,
                         capture, ("--split", "capture"), frames_shown(capture, fps)))

    for name in sorted(ds.splits, key=lambda s: (s not in ("train", "val"), s)):
        frames = ds.split(name)
        if frames:
            out.append(Track(f"split {name} ({len(frames)} frames)",  # at render's rate
                             ds.expression_matrix(frames), split_fps(ds, frames) or fps,
                             frames, ("--split", name)))
    return out


def tour_track(ds: Dataset, names: list[str], base: np.ndarray, companions=None
               ) -> Track | None:
    """`tour`: each control the training frames show, in turn, from `base` to an end of
    its range and back (`render --expressions tour`); None where the dataset's controls
    are not the run's or none moves."""
    if ds.expression_names != names:
        return None
    try:
        seq = from_items(["tour"], names, base, None, companions, training_expressions(ds))
    except UserError:
        return None
    return Track(f"tour ({len(seq)} frames)", seq.values, 30.0,
                 render_args=("--expressions", "tour"))


def load_track_file(path: str | Path, names: list[str]) -> Track:
    """A `flamenerf track` JSON file or a Live Link Face take (at the take's rate), with its
    channels matched to `names` by name (channels the run lacks are dropped, controls the
    file lacks stay 0)."""
    if Path(path).suffix.lower() == ".csv" and is_take(Path(path)):
        seq = load_take(Path(path), names)
        return Track(f"take {Path(path).name} ({len(seq)} frames)", seq.values,
                     float(seq.fps), render_args=("--expressions", str(path)))
    tr = load_expressions(path)
    mat, _ = map_by_name(tr.frames, tr.names, names, str(path), strict=False,
                         what=f"{len(tr.names)} expression channels",
                         hint="; track with the run's --face-model")
    return Track(f"file {Path(path).name} ({len(mat)} frames)", mat, float(tr.fps),
                 render_args=("--expressions", str(path)))


def slider_range(ds: Dataset) -> tuple[float, float]:
    """Range of the expression sliders: [0, 1] for blendshape-style scores (ARKit, the
    synthetic rig), else the data's range with a margin, rounded outwards."""
    x = ds.expression_matrix(ds.frames)
    lo, hi = float(x.min()), float(x.max())
    if lo >= -1e-6 and hi <= 1 + 1e-6:
        return 0.0, 1.0
    m = 0.25 * (hi - lo)
    return float(np.floor(min(lo - m, 0.0))), float(np.ceil(max(hi + m, 0.0)))

