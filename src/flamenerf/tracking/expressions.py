"""Expression tracks: the JSON file `flamenerf track` writes and `flamenerf render --drive`
reads, and expression transfer relative to each subject's neutral face.

Format (docs/preprocessing.md)::

    {
      "format": "flamenerf-expressions", "version": 1,
      "kind": "arkit",                  # or "flame": must match the dataset's expression_model
      "names": ["_neutral", "browDownLeft", ...],   # one per channel
      "fps": 30.0,                      # rate of the entries of "frames"
      "frames": [[0.0, 0.01, ...], ...],            # one expression vector per entry
      "source_frames": [0, 1, 2, ...],  # video frame index of each entry
      "times": [0.0, 0.0333, ...],      # seconds
      "dropped": [{"source_frame": 17, "time": 0.567, "reason": "no face detected"}],
      "source": {"video": "...", "tool": "flamenerf track", "version": "0.1.0"},
      "transfer": null | {"mode": "relative", "driver_neutral": [...],
                          "subject_neutral": [...], "subject": "data/me"}
    }

Only "names" and "frames" are required when reading; "fps" defaults to 30.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from flamenerf.data.dataset import Dataset
from flamenerf.data.video import check_fps
from flamenerf.errors import UserError
from flamenerf.io import atomic_write_text, read_json

FORMAT = "flamenerf-expressions"
VERSION = 1


@dataclass
class ExpressionTrack:
    names: list[str]
    frames: np.ndarray  # (T, D) float32
    fps: float = 30.0
    kind: str = "unknown"
    source_frames: list[int] | None = None
    times: list[float] | None = None
    dropped: list[dict] = field(default_factory=list)
    source: dict[str, Any] = field(default_factory=dict)
    transfer: dict[str, Any] | None = None
    head_pose: np.ndarray | None = None  # (T, 6) yaw, pitch, roll, x, y, z vs the first frame
    face_box: np.ndarray | None = None  # (T, 4) x0, y0, x1, y1 source px (pictures; not saved)

    def to_json(self) -> dict:
        return {
            "format": FORMAT, "version": VERSION, "kind": self.kind, "names": self.names,
            "fps": self.fps,
            "frames": [[round(float(x), 6) for x in row] for row in self.frames],
            "source_frames": self.source_frames, "times": self.times,
            "dropped": self.dropped, "source": self.source, "transfer": self.transfer,
            "head_pose": None if self.head_pose is None else [
                dict(zip(("yaw", "pitch", "roll"), (round(float(x), 3) for x in r[:3])))
                for r in self.head_pose],
        }


def save_expressions(path: str | os.PathLike, track: ExpressionTrack) -> Path:
    """Write atomically (flamenerf.io: temp file + rename)."""
    path = Path(path)
    atomic_write_text(path, json.dumps(track.to_json(), indent=None, separators=(",", ":")))
    return path


def load_expressions(path: str | os.PathLike) -> ExpressionTrack:
    """Read and validate; any problem is one UserError naming the file."""
    path = Path(path)
    d = read_json(path, "expression file")
    if not isinstance(d, dict) or "names" not in d or "frames" not in d:
        raise UserError(f"{path}: needs an object with 'names' and 'frames'")
    names = d["names"]
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise UserError(f"{path}: 'names' must be a list of strings")
    try:
        frames = np.asarray(d["frames"], np.float32)
    except (TypeError, ValueError):
        raise UserError(f"{path}: 'frames' must be a list of equal-length number lists") \
            from None
    if frames.ndim != 2 or frames.shape[1] != len(names) or len(frames) == 0:
        raise UserError(f"{path}: 'frames' must be a non-empty list of vectors of "
                        f"{len(names)} numbers (one per name), got shape {frames.shape}")
    if not np.all(np.isfinite(frames)):
        raise UserError(f"{path}: 'frames' contains non-finite values")
    fps = d.get("fps", 30.0)
    fps = check_fps(fps, f"{path}: 'fps'")
    return ExpressionTrack(names=names, frames=frames, fps=float(fps),
                           kind=str(d.get("kind", "unknown")),
                           source_frames=d.get("source_frames"), times=d.get("times"),
                           dropped=d.get("dropped") or [], source=d.get("source") or {},
                           transfer=d.get("transfer"))


def estimate_neutral(expr: np.ndarray, k: int = 5) -> tuple[np.ndarray, list[int]]:
    """A subject's neutral expression: the mean of the k frames with the smallest expression
    norm (ARKit scores are >= 0 and FLAME's neutral is 0, so 'smallest' means 'calmest').
    Returns the vector and the frames used."""
    expr = np.asarray(expr, np.float64)
    idx = np.argsort(np.linalg.norm(expr, axis=1))[: max(1, min(k, len(expr)))]
    return expr[idx].mean(0), sorted(int(i) for i in idx)


def transfer_relative(drive: np.ndarray, driver_neutral: np.ndarray,
                      subject_neutral: np.ndarray, kind: str,
                      gains: np.ndarray | None = None) -> np.ndarray:
    """NerFACE-style cross-subject transfer: subject_neutral + gains · (drive -
    driver_neutral), gains (E,) 1 unless given (`range_gains`). ARKit scores are clipped
    back to [0, 1]."""
    delta = np.asarray(drive) - driver_neutral[None]
    if gains is not None:
        delta = delta * np.asarray(gains)[None]
    out = subject_neutral[None] + delta
    if kind == "arkit":
        out = np.clip(out, 0.0, 1.0)
    return out.astype(np.float32)


REACH = 99.0
"""The percentile of a control's values that stands for the furthest a face takes it (the
largest value is often one frame's tracking glitch)."""
MIN_REACH = 0.1
GAIN_RANGE = (0.25, 4.0)


def range_gains(drive: np.ndarray, driver_neutral: np.ndarray, subject: np.ndarray,
                subject_neutral: np.ndarray) -> np.ndarray:
    """Per control, how much the driver's motion is scaled so that the furthest the driver
    takes it from their neutral (its REACH percentile over `drive` (T, E)) lands on the
    furthest the subject's frames (N, E) take it: a driver who smiles broadly gives the
    subject's broadest smile instead of clipping at it, and a small talker's jaw moves the
    subject's as far as the subject's own. 1 where either moves it by less than MIN_REACH
    (nothing to match: a control the subject never shows stays near its range, as `render`
    says); within GAIN_RANGE. -> (E,)"""
    d_reach = np.percentile(np.asarray(drive, np.float64), REACH, axis=0) - driver_neutral
    s_reach = np.percentile(np.asarray(subject, np.float64), REACH, axis=0) - subject_neutral
    ok = (d_reach >= MIN_REACH) & (s_reach >= MIN_REACH)
    gains = np.where(ok, s_reach / np.where(ok, d_reach, 1.0), 1.0)
    return np.clip(gains, *GAIN_RANGE)


def transfer_to_subject(track: ExpressionTrack, subject: Dataset,
                        driver_neutral_frame: int | None = None,
                        mode: str = "relative") -> ExpressionTrack:
    """`track` re-expressed relative to the subject dataset's neutral face
    (`transfer_relative`), with the record of what was used in `transfer`.

    The subject's neutral comes from its capture frames, the driver's from the track
    (`estimate_neutral`) or from video frame `driver_neutral_frame`. `mode` "range": each
    control's motion is also scaled from the driver's reach to the subject's
    (`range_gains`). The expression models must match (same names)."""
    from dataclasses import replace

    if subject.expression_names != track.names:
        raise UserError(
            f"{subject.root}: its expression model ({subject.expression_kind}, "
            f"{subject.expression_dim} values) differs from this track's ({track.kind}, "
            f"{len(track.names)}); use the same --face-model")
    capture = subject.capture()
    s_frames = subject.expression_matrix(capture)
    s_neutral, s_used = estimate_neutral(s_frames)
    if driver_neutral_frame is not None:
        if driver_neutral_frame not in (track.source_frames or []):
            raise UserError(f"{track.source.get('video', 'the track')}: frame "
                            f"{driver_neutral_frame} was not tracked (pick a selected frame "
                            "with a face)")
        d_neutral = track.frames[track.source_frames.index(driver_neutral_frame)].astype(
            np.float64)
        d_used = [driver_neutral_frame]
    else:
        d_neutral, used = estimate_neutral(track.frames)
        d_used = [track.source_frames[i] for i in used] if track.source_frames else used
    gains = (range_gains(track.frames, d_neutral, s_frames, s_neutral) if mode == "range"
             else None)
    return replace(
        track, frames=transfer_relative(track.frames, d_neutral, s_neutral, track.kind, gains),
        transfer={"mode": mode, "subject": str(subject.root),
                  **({} if gains is None else {"gains": np.round(gains, 4).tolist()}),
                  "subject_neutral": np.round(s_neutral, 6).tolist(),
                  "subject_neutral_frames": [capture[i].frame_index for i in s_used],
                  "driver_neutral": np.round(d_neutral, 6).tolist(),
                  "driver_neutral_frames": d_used})
