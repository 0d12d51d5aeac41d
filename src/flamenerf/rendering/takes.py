"""ARKit takes as the iPhone's Live Link Face app exports them: a CSV with the header
`Timecode,BlendShapeCount,EyeBlinkLeft,...,TongueOut,HeadYaw,HeadPitch,HeadRoll,
LeftEyeYaw,...,RightEyeRoll` and one row per tracked frame, its time an SMPTE timecode
`HH:MM:SS:FF.mmm` (FF the frame within the second at the timecode's rate, .mmm the
fraction of a frame).

A take becomes an `ExpressionSequence` (rendering/expressions.load_take) on an even grid of frame times (its own rate, or
the one asked for), its blendshapes mapped by name onto the run's controls (ARKit's names
with a lower-case first letter) and its head angles as `head_pose` rows (`render
--head-pose take`)."""

from __future__ import annotations

# imported (through rendering/expressions.py) to build `flamenerf --help`: tracking.driving
# is imported where a take's head turns are read

import csv
import re
from pathlib import Path

import numpy as np

from flamenerf.errors import UserError
from flamenerf.geometry import euler_head

TIMECODE = re.compile(r"^(\d{1,2}):(\d{2}):(\d{2})[:;](\d{1,3})(\.\d+)?$")
# timecode rates Live Link Face and video use; a take's is the smallest above its largest FF
TIMECODE_RATES = (24, 25, 30, 50, 60)
HEAD_COLUMNS = ("HeadYaw", "HeadPitch", "HeadRoll")
# not expression controls: the frame's time, how many blendshapes it carries, and rotations
NOT_CONTROLS = {"Timecode", "BlendShapeCount", *HEAD_COLUMNS,
                *(f"{eye}Eye{angle}" for eye in ("Left", "Right")
                  for angle in ("Yaw", "Pitch", "Roll"))}
SNAP = 0.01  # a take whose rows come within 1% of a standard rate plays at that rate


def is_take(path: Path) -> bool:
    """Whether a CSV file's first row is a Live Link Face header (starts with Timecode)."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            first = next(csv.reader(f), [])
    except (UnicodeDecodeError, csv.Error, OSError):
        return False
    return bool(first) and first[0].strip().lower() == "timecode"


def control_name(column: str) -> str:
    """A Live Link Face column -> ARKit's blendshape name: EyeBlinkLeft -> eyeBlinkLeft."""
    return column[:1].lower() + column[1:]


def parse_timecode(text: str, where: str) -> tuple[int, int, int, int, float]:
    """`HH:MM:SS:FF.mmm` -> (hours, minutes, seconds, frame, fraction of a frame)."""
    m = TIMECODE.match(text.strip())
    if m is None or int(m[2]) > 59 or int(m[3]) > 59:
        raise UserError(f"{where}: timecode {text.strip()!r} is not HH:MM:SS:FF.mmm")
    return int(m[1]), int(m[2]), int(m[3]), int(m[4]), float(m[5] or 0.0)


def timecode_rate(codes: list[tuple[int, int, int, int, float]]) -> tuple[int, str | None]:
    """The rate of a take's timecodes, from their frame numbers: the smallest standard rate
    (TIMECODE_RATES) above the largest FF, which a take spanning a change of second has
    reached (the rows come at least as often as the timecode's frames, or every other one
    at most: 58 still gives 60). -> (rate, a note where it is a guess: a take within one
    second, or frame numbers beyond 60 fps, which are taken as their largest + 1)."""
    top = max(c[3] for c in codes)
    rate = next((r for r in TIMECODE_RATES if r > top), None)
    if rate is None:
        return top + 1, (f"timecode frames up to {top}, beyond a {TIMECODE_RATES[-1]} fps "
                         f"timecode: taken as {top + 1} fps")
    if len({c[:3] for c in codes}) == 1:
        return rate, (f"the timecodes stay within one second: their rate is taken as {rate} "
                      f"fps, the smallest standard rate above their largest frame ({top})")
    return rate, None


def frame_rate(times: np.ndarray) -> float | None:
    """The rate a take's rows come at: one over their median interval, snapped to a
    standard rate within SNAP (the phone's clock drifts a little from the timecode's);
    None for a single row."""
    if len(times) < 2:
        return None
    rate = 1.0 / float(np.median(np.diff(times)))
    near = min(TIMECODE_RATES, key=lambda r: abs(r - rate))
    return float(near) if abs(near - rate) <= SNAP * near else round(rate, 3)


def resample(times: np.ndarray, values: np.ndarray, rate: float) -> np.ndarray:
    """values (T, K) at `times` (seconds, increasing) -> on the even grid from the first
    time at `rate`, as long as the take (its last row lasting a row's median interval),
    to the nearest frame, linearly between rows (a frame the phone dropped, or where it
    lost the face, is bridged)."""
    step = float(np.median(np.diff(times))) if len(times) > 1 else 1.0 / rate
    num = max(1, int(round((times[-1] - times[0] + step) * rate)))
    grid = times[0] + np.arange(num) / rate
    return np.stack([np.interp(grid, times, values[:, j]) for j in range(values.shape[1])],
                    -1).astype(np.float32)


def head_turns(angles: np.ndarray) -> np.ndarray:
    """Live Link Face's HeadYaw, HeadPitch, HeadRoll rows (T, 3) -> `head_pose` rows (T, 6):
    yaw, pitch, roll in degrees in the head's own axes relative to the first frame
    (`tracking.driving.relative_head_pose`, as a driving video's), x, y, z = 0.

    Units: radians. Faceit's Live Link Face CSV importer (its EpicMocapImporter) reads these
    columns as radians, and the takes' eye columns agree: ARKit's full eyeLookIn/Out moves
    LeftEyeYaw by about 0.6, i.e. 34 degrees (108 if they were the Unreal ARKit plugin's
    degrees / 180). Signs, from the same eye columns (Unreal's ARKit conversion makes head
    and eye angles alike): yaw is < 0 looking to the subject's left, pitch < 0 looking up;
    roll is taken to flip with yaw, as it does in that conversion (a right-handed turn
    about ARKit's z, out of the face, negated), so HeadRoll > 0 tilts the top of the head
    to the subject's left. Not checked against a recorded take with head turns.
    """
    from flamenerf.tracking.driving import relative_head_pose

    deg = np.degrees(np.asarray(angles, np.float64))
    # euler_head's yaw > 0 turns to the subject's left, pitch > 0 raises the chin, roll > 0
    # tilts to the subject's left
    T = np.tile(np.eye(4), (len(deg), 1, 1))
    T[:, :3, :3] = [euler_head(-y, -p, r) for y, p, r in deg]
    return relative_head_pose(T)


def read_take(path: Path) -> tuple[list[str], np.ndarray, np.ndarray, list[str]]:
    """A take's rows -> (its column names after Timecode, their values (T, K), the rows'
    times in seconds from the first (T,), notes). Rows without a face (BlendShapeCount 0)
    are left out. Each fault is a one-line UserError naming the file and its row (the
    header is row 1)."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = [(i + 1, r) for i, r in enumerate(csv.reader(f))]
    except (UnicodeDecodeError, csv.Error):
        raise UserError(f"{path}: not a text CSV file") from None
    header = [c.strip() for c in rows[0][1]]
    body = [(n, r) for n, r in rows[1:] if r and any(c.strip() for c in r)]
    if not body:
        raise UserError(f"{path}: a Live Link Face take without rows")
    codes, values = [], []
    for n, r in body:
        where = f"{path}: row {n}"
        if len(r) != len(header):
            raise UserError(f"{where} has {len(r)} values, the header names {len(header)}")
        codes.append(parse_timecode(r[0], where))
        try:
            values.append([float(c) for c in r[1:]])
        except ValueError:
            bad = next(j for j, c in enumerate(r[1:], 1) if not _is_number(c))
            raise UserError(f"{where}: {header[bad]} is not a number ({r[bad].strip()!r})"
                            ) from None
        if not np.all(np.isfinite(values[-1])):
            raise UserError(f"{where}: contains a non-finite value")
    rate, note = timecode_rate(codes)
    times = np.array([h * 3600 + m * 60 + s + (ff + frac) / rate
                      for h, m, s, ff, frac in codes])
    for k in np.nonzero(np.diff(times) <= 0)[0]:
        raise UserError(f"{path}: row {body[k + 1][0]}: timecode {body[k + 1][1][0].strip()} "
                        f"does not come after row {body[k][0]}'s ({body[k][1][0].strip()})")
    arr = np.asarray(values, np.float64)
    notes = [f"{path}: {note}"] if note else []
    if "BlendShapeCount" in header:
        face = arr[:, header.index("BlendShapeCount") - 1] > 0
        if not face.any():
            raise UserError(f"{path}: no row has a face (BlendShapeCount is 0 in every row)")
        if not face.all():
            notes.append(f"{path}: {int((~face).sum())} rows without a face (BlendShapeCount "
                         "0) bridged from their neighbours")
        arr, times = arr[face], times[face]
    return header[1:], arr, times - times[0], notes


def _is_number(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False
