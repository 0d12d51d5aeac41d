"""Expression sources for re-animation: files, named controls, dataset splits, videos.

Every source becomes an `ExpressionSequence` whose vectors are in the run's control order
(`Run.expression_names`). Sources that name their controls (a `flamenerf track` JSON, a CSV
with a header, `name=value` keyframes) are mapped by name: controls the source lacks are 0,
controls the run lacks are dropped (with a note) for tracks and CSV files, and are an error
where a person typed them (keyframes, JSON objects of name: value).

Accepted `--expressions` values:
  FILE.json   a `flamenerf track` file {"names": [...], "frames": [[...], ...], "fps": f}; a
              list of vectors; an object {name: value} (one expression); a list of such
              objects (one per frame).
  FILE.npy    an array (T, E) or (E,) in the run's control order.
  FILE.csv    one vector per row; an optional header row of control names. Or an ARKit
              take as the Live Link Face app exports it (a header starting with
              Timecode): its timecodes give the frames' times (rendering/takes.py).
  KEYFRAMES   one or more items `name=value[,name=value...]`: the video eases from the base
              expression (frame 0's by default) to each keyframe in turn and back; controls
              a keyframe does not name keep the base's value, except, by default, their
              companions: the controls of the same part of the face and side that the
              tracker reads with them (data/companions.py).
  tour        every control the training frames show, one after the other: from the base
              up to the control's 99th percentile in the training frames and back (down to
              its 1st where the base leaves no room, and for signed controls such as
              FLAME's where that end is farther); a Left/Right pair together; companions as
              for keyframes. What a run can do with its clip's expressions, at a glance.
"""

from __future__ import annotations

# imported (through rendering/videos.py) to build `flamenerf --help`: tracking a driving
# video is imported inside the functions that do it

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from flamenerf.data.companions import Companions
from flamenerf.errors import UserError
from flamenerf.io import read_json
from flamenerf.keyvalues import parse_assignments, resolve_control, suggest
from flamenerf.rendering import takes
from flamenerf.data.dataset_checks import MAX_CONTROL
from flamenerf.data.expression_range import MIN_SPAN, span
from flamenerf.data.face_parts import part_and_side
from flamenerf.data.video import iter_frames, probe_video
from flamenerf.images import resize_image

FILE_SUFFIXES = (".json", ".npy", ".csv")
KEYFRAME_FRAMES = 60  # a keyframe sequence's length unless --frames says
# the tour's controls and how far it takes them: a control whose 99th percentile in the
# training frames is at least MIN_SPAN above its 1st, to whichever of the two is farther
# from the base (signed controls such as FLAME's go either way). Not eval's 5th-95th
# (data/expression_range.span): a clip that smiles in a few frames of a hundred (the shared
# expressions clip: 95th 0.06-0.10, 99th 0.24-0.49) has learnt a smile the 95th does not
# show; the 99th, unlike the largest, is not one frame's tracking glitch
TOUR_QUANTILES = (1.0, 99.0)
TOUR_FRAMES = 24  # a tour's frames a control (0.8 s at 30 fps; one more in all) unless
# --frames says


@dataclass
class ExpressionSequence:
    values: np.ndarray  # (T, E) float32 in the run's control order
    label: str  # what it came from, for logs and file names
    fps: float | None = None  # the source's frame rate, if it has one
    cameras: np.ndarray | None = None  # (T, 4, 4) the source's own cameras (a split)
    vertices: np.ndarray | None = None  # (T, V, 3) per-frame face mesh (a split)
    driving: Callable[[int], np.ndarray] | None = None  # frame i's driving image, uint8
    resizable: bool = False  # keyframes: the sequence adapts to any number of frames
    head_pose: np.ndarray | None = None  # (T, 6) a driving video's or a take's head turns
    take: Path | None = None  # the Live Link Face take it came from (--head-pose take)
    notes: tuple[str, ...] = ()
    times: np.ndarray | None = None
    """(T,) each frame's time in its source, seconds (a driving video's tracked frames): what
    keeps the picture in step with the source's sound (rendering/soundtrack.py)."""

    def __len__(self) -> int:
        return len(self.values)


def source_head_pose(word: str, seq: ExpressionSequence | None, log=print) -> np.ndarray:
    """`--head-pose drive` / `--head-pose take`: the head's turns (T, 6) of the driving
    video / the Live Link Face take `seq` came from; each word only its own source, so that
    a command says where the head's motion comes from."""
    if word == "drive":
        if seq is None or seq.take is not None or seq.head_pose is None:
            raise UserError("--head-pose drive: takes the head's turns from a driving video; "
                            "give one with --drive"
                            + (" (a take's: --head-pose take)" if seq and seq.take else ""))
        return np.asarray(seq.head_pose, np.float64)
    if seq is None or seq.take is None:
        raise UserError("--head-pose take: takes the head's turns from a Live Link Face take; "
                        "give one with --expressions take.csv")
    if seq.head_pose is None:
        raise UserError(f"--head-pose take: {seq.take} has no HeadYaw, HeadPitch, HeadRoll "
                        "columns")
    if not np.any(seq.head_pose):
        log(f"note: {seq.take}: its head columns are 0 in every row (recorded without head "
            "rotation): the head stays at frame 0's pose")
    return np.asarray(seq.head_pose, np.float64)


def map_by_name(values: np.ndarray, src_names: list[str], names: list[str], where: str,
                strict: bool, what: str = "controls", hint: str = ""
                ) -> tuple[np.ndarray, list[str]]:
    """Columns of `values` (T, len(src_names)) onto `names`; missing controls are 0.
    -> (T, len(names)), the source's names the run lacks (an error when `strict`).
    The error when no name matches calls the source's columns `what` and ends with `hint`."""
    values = np.asarray(values, np.float32)
    index = {n: i for i, n in enumerate(names)}
    twice = sorted({n for n in src_names if src_names.count(n) > 1})
    if twice:
        raise UserError(f"{where}: {twice[0]} is named twice")
    unknown = [n for n in src_names if n not in index]
    if strict and unknown:
        raise UserError(f"{where}: unknown control {unknown[0]!r}{suggest(unknown[0], names)} "
                        f"(this run's controls: {', '.join(names)})")
    if len(unknown) == len(src_names):
        raise UserError(f"{where}: none of its {what} ({', '.join(src_names[:6])}"
                        f"{', ...' if len(src_names) > 6 else ''}) is one of this run's "
                        f"({', '.join(names)}){hint}")
    out = np.zeros((len(values), len(names)), np.float32)
    for j, n in enumerate(src_names):
        if n in index:
            out[:, index[n]] = values[:, j]
    return out, unknown


def parse_keyframe(item: str, names: list[str], base: np.ndarray,
                   companions: Companions | None = None) -> np.ndarray:
    """`name=value[,name=value...]` -> the base expression with those controls set, and
    with their companions (data/companions.py) moved along when given."""
    index = {n: i for i, n in enumerate(names)}
    values = {index[name]: v for name, v in keyframe_values(item, names).items()}
    bounded(np.array(list(values.values())), f"--expressions {item!r}")
    return keyframe(base, values, companions)


def keyframe_values(item: str, names: list[str]) -> dict[str, float]:
    """A keyframe's `name=value` items -> {control: value}: a name may be a pair's stem
    (both sides) or a control in another case, as in an edit (`keyvalues.resolve_control`)."""
    parts = []  # a pair's stem or another case, written out as the controls it means
    for part in item.split(","):
        name, eq, value = part.partition("=")
        found = resolve_control(name.strip(), names) if eq else None
        parts += [f"{n}={value}" for n in found] if found else [part]
    return parse_assignments(",".join(parts), names, "--expressions", "control",
                             " (or a .json/.npy/.csv file)", typed=item)


def keyframe(base: np.ndarray, values: dict[int, float],
             companions: Companions | None = None) -> np.ndarray:
    """The base expression (E,) with the controls `values` ({index: value}) set, and their
    companions moved along when given."""
    if companions is not None:
        return companions.complete(np.asarray(base, np.float32), values)
    vec = np.array(base, np.float32, copy=True)
    for k, v in values.items():
        vec[k] = v
    return vec


def ease(u: np.ndarray) -> np.ndarray:
    """0 -> 1 for u in [0, 1], with no jolt at either end (cosine): how keyframes and an
    edit limited in time come in and go."""
    return (1 - np.cos(np.pi * np.clip(u, 0.0, 1.0))) / 2


def keyframe_sequence(keys: np.ndarray, base: np.ndarray, num: int) -> np.ndarray:
    """Ease base -> keys[0] -> ... -> keys[-1] -> base over `num` frames."""
    pts = np.concatenate([base[None], np.asarray(keys, np.float32), base[None]])
    if num == 1:
        return pts[1:2].copy()
    u = np.arange(num) / (num - 1) * (len(pts) - 1)
    seg = np.minimum(np.floor(u).astype(int), len(pts) - 2)
    w = ease(u - seg)
    return (pts[seg] * (1 - w[:, None]) + pts[seg + 1] * w[:, None]).astype(np.float32)


def is_file_arg(items: list[str]) -> bool:
    return len(items) == 1 and (Path(items[0]).suffix.lower() in FILE_SUFFIXES
                                or Path(items[0]).is_file())


def _pair_stem(name: str) -> str:
    """The name a control shares with its other side (`mouthSmileLeft` -> `mouthSmile`),
    else its own: ARKit's sideways moves (data/face_parts: not sided) and gaze
    (eyeLookInLeft turns the left eye to the nose) are not one motion on two sides."""
    stem = re.sub(r"(Left|Right)$", "", name)
    if not stem or not part_and_side(name)[1] or stem.startswith("eyeLook"):
        return name
    return stem


def tour_keyframes(training: np.ndarray, names: list[str], base: np.ndarray,
                   companions: Companions | None = None) -> tuple[np.ndarray, list[str]]:
    """`--expressions tour`'s keyframes: for each control the training expressions (N, E)
    show (TOUR_QUANTILES), in the run's order, the base with it moved to one end of its
    range, then the base again. Scores in [0, 1] (ARKit's, the built-in rig's: 0 is at
    rest) go up, to the 99th percentile, unless the base leaves less than MIN_SPAN of it;
    then, and for signed controls (FLAME's), to the end farther from the base. A Left/Right
    pair is one keyframe, both sides to the same end (a side that does not move itself
    keeps the base). -> keys (2K - 1, E) and the K keyframes' names (a pair by its
    stem)."""
    lo, top = span(training, TOUR_QUANTILES)
    base = np.asarray(base, np.float32)
    moves = top - lo >= MIN_SPAN
    scores = bool(np.min(training) >= -1e-6 and np.max(training) <= 1 + 1e-6)
    groups: dict[str, list[int]] = {}
    for j, name in enumerate(names):
        if moves[j]:
            groups.setdefault(_pair_stem(name), []).append(j)
    if not groups:
        raise UserError("--expressions tour: no control moves in the training frames (each "
                        f"one's 1st-99th percentile span is under {MIN_SPAN})")
    keys = []
    for js in groups.values():
        rise = np.clip(top[js] - base[js], 0, None).sum()
        up = (scores and rise >= MIN_SPAN) or rise >= np.clip(base[js] - lo[js], 0, None).sum()
        keys += [keyframe(base, {j: float(top[j] if up else lo[j]) for j in js}, companions),
                 base]
    return np.stack(keys[:-1]), [k if len(js) > 1 else names[js[0]] for k, js in groups.items()]


def from_items(items: list[str], names: list[str], base: np.ndarray, num: int | None,
               companions: Companions | None = None, training: np.ndarray | None = None,
               fps: float | None = None) -> ExpressionSequence:
    """`--expressions` values: one file, `tour` (needs the `training` expressions (N, E)),
    or keyframes (with `companions`: the controls the tracker reads with the named ones
    move too; files are taken as they are). `num` frames (None: KEYFRAME_FRAMES, a tour
    TOUR_FRAMES a control); `fps`: the rate a timed file (an ARKit take) is resampled to
    (None: its own)."""
    if not items:
        raise UserError("--expressions: give a file, `tour` or name=value keyframes")
    if "tour" in items and len(items) > 1:
        raise UserError("--expressions: `tour` goes alone, not with keyframes or a file")
    if items == ["tour"]:
        if training is None:
            raise UserError("--expressions tour: needs the run's training frames")
        keys, shown = tour_keyframes(training, names, base, companions)
        # + 1: every keyframe then falls on a frame, at its full value
        num = num or TOUR_FRAMES * len(shown) + 1
        notes = [f"the tour: {', '.join(shown)}, each to the end of its range in the "
                 f"training frames and back"]
        if num < 2 * len(shown) + 1:
            notes.append(f"{num} frames for a tour of {len(shown)}: too few for each control "
                         f"to reach its peak (at least {2 * len(shown) + 1})")
        return ExpressionSequence(keyframe_sequence(keys, base, num), label="tour",
                                  resizable=True, notes=tuple(notes))
    if is_file_arg(items):
        return load_file(Path(items[0]), names, rate=fps)
    num = num or KEYFRAME_FRAMES
    keys = np.stack([parse_keyframe(it, names, base, companions) for it in items])
    notes = ()
    if companions is not None:
        moved = sorted({names[j] for key in keys for j in np.nonzero(key != base)[0]}
                       - {n for it in items for n in keyframe_values(it, names)})
        if moved:
            notes = (f"keyframes also move {', '.join(moved)}: the controls the tracker reads "
                     "with the named ones (--no-companions to leave them)",)
    return ExpressionSequence(keyframe_sequence(keys, base, num), label="keyframes",
                              resizable=True, notes=notes)


def _vectors(arr, where: str, names: list[str]) -> np.ndarray:
    try:
        a = np.asarray(arr, np.float32)
    except (TypeError, ValueError):
        raise UserError(f"{where}: expected equal-length lists of numbers") from None
    if a.ndim == 1:
        a = a[None]
    if a.ndim != 2 or len(a) == 0:
        raise UserError(f"{where}: expected a non-empty list of vectors, got shape {a.shape}")
    if a.shape[1] != len(names):
        raise UserError(f"{where}: has {a.shape[1]} values per frame, this run has "
                        f"{len(names)} controls ({', '.join(names)}); name the controls "
                        "(a CSV header, or name: value objects) to map them by name")
    if not np.all(np.isfinite(a)):
        raise UserError(f"{where}: contains non-finite values")
    return a


def load_file(path: Path, names: list[str], rate: float | None = None) -> ExpressionSequence:
    """One expression file (see the module doc) -> a sequence in the run's control order;
    an ARKit take at its own rate or resampled to `rate`."""
    if path.is_dir():
        raise UserError(f"{path}: is a folder; give the expression file itself")
    if not path.is_file():
        raise UserError(f"{path}: expression file does not exist")
    suffix = path.suffix.lower()
    notes: list[str] = []
    fps = None
    if suffix == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except Exception as e:  # noqa: BLE001 - any parse failure is the file's fault
            raise UserError(f"{path}: not a readable .npy array ({type(e).__name__})") from None
        values = _vectors(arr, str(path), names)
    elif suffix == ".csv" and takes.is_take(path):
        seq = load_take(path, names, rate)
        bounded(seq.values, str(path))
        return seq
    elif suffix == ".csv":
        values, notes = _load_csv(path, names)
    else:
        d = read_json(path, "expression file")
        if isinstance(d, dict) and "frames" in d and "names" in d:
            from flamenerf.tracking.expressions import load_expressions

            tr = load_expressions(path)
            values, unknown = map_by_name(tr.frames, tr.names, names, str(path), strict=False)
            if unknown:
                notes.append(f"{path}: ignored {len(unknown)} controls this run lacks "
                             f"({', '.join(unknown[:5])}{', ...' if len(unknown) > 5 else ''})")
            fps = tr.fps
        elif isinstance(d, dict):
            values = _named_rows([d], names, str(path))
        elif isinstance(d, list) and d and all(isinstance(r, dict) for r in d):
            values = _named_rows(d, names, str(path))
        else:
            values = _vectors(d, str(path), names)
    return ExpressionSequence(bounded(values, str(path)).astype(np.float32), label=path.stem,
                              fps=fps, notes=tuple(notes))


def load_take(path: Path, names: list[str], fps: float | None = None) -> ExpressionSequence:
    """A Live Link Face take (rendering/takes.py) -> an ExpressionSequence in the run's
    control order, at its own rate (`takes.frame_rate`) or `fps`, with the head's turns as
    `head_pose` where the take has the head columns (all three)."""
    columns, arr, times, notes = takes.read_take(path)
    rate = fps or takes.frame_rate(times) or 30.0
    if fps is None and len(times) < 2:
        notes.append(f"{path}: a take of one row: shown as one frame at {rate:g} fps")
    controls = [j for j, c in enumerate(columns) if c not in takes.NOT_CONTROLS]
    values, unknown = map_by_name(takes.resample(times, arr[:, controls], rate),
                                  [takes.control_name(columns[j]) for j in controls], names,
                                  str(path), strict=False, what="blendshapes")
    if unknown:
        notes.append(f"{path}: ignored blendshapes this run lacks ({', '.join(unknown[:5])}"
                     f"{', ...' if len(unknown) > 5 else ''})")
    head = None
    if all(c in columns for c in takes.HEAD_COLUMNS):
        head_columns = [columns.index(c) for c in takes.HEAD_COLUMNS]
        angles = takes.resample(times, arr[:, head_columns], rate)
        head = takes.head_turns(angles)
    return ExpressionSequence(values, label=path.stem, fps=rate, head_pose=head,
                              take=path, notes=tuple(notes))


def bounded(values: np.ndarray, where: str) -> np.ndarray:
    """values, unless one is beyond ±MAX_CONTROL (a one-line UserError naming `where`), as
    datasets' expressions are refused: no expression model means such a value, and float32
    arithmetic turns it into inf."""
    v = np.asarray(values)
    if v.size and float(np.abs(v).max()) > MAX_CONTROL:
        raise UserError(f"{where}: a value of {float(np.abs(v).max()):.3g} (expression values "
                        f"are at most {MAX_CONTROL:g} in size)")
    return values


def _named_rows(rows: list[dict], names: list[str], where: str) -> np.ndarray:
    if not any(rows):  # `{}` would render every control at 0, which nobody writes on purpose
        raise UserError(f"{where}: names no controls (give name: value pairs, e.g. "
                        f"{{\"{names[0]}\": 0.5}})")
    out = np.zeros((len(rows), len(names)), np.float32)
    index = {n: i for i, n in enumerate(names)}
    for t, row in enumerate(rows):
        for k, v in row.items():
            if k not in index:
                raise UserError(f"{where}: unknown control {k!r}{suggest(k, names)} (this "
                                f"run's controls: {', '.join(names)})")
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not np.isfinite(v):
                raise UserError(f"{where}: {k} must be a finite number, got {v!r}")
            out[t, index[k]] = v
    return out


def _load_csv(path: Path, names: list[str]) -> tuple[np.ndarray, list[str]]:
    import csv

    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = [r for r in csv.reader(f) if r and any(c.strip() for c in r)]
    except (UnicodeDecodeError, csv.Error):
        raise UserError(f"{path}: not a text CSV file") from None
    if not rows:
        raise UserError(f"{path}: empty CSV file")

    def numeric(r):
        try:
            [float(c) for c in r]
            return True
        except ValueError:
            return False

    header = None if numeric(rows[0]) else [c.strip() for c in rows[0]]
    body = rows[1:] if header is not None else rows
    if not body:
        raise UserError(f"{path}: no data rows")
    for i, r in enumerate(body):
        if not numeric(r):
            raise UserError(f"{path}: row {i + 1 + (header is not None)} is not all numbers")
    try:
        arr = np.asarray([[float(c) for c in r] for r in body], np.float32)
    except ValueError:
        raise UserError(f"{path}: rows must have equal lengths") from None
    if header is None:
        return _vectors(arr, str(path), names), []
    if arr.ndim != 2 or arr.shape[1] != len(header):
        raise UserError(f"{path}: rows must have {len(header)} values, one per header name")
    if not np.all(np.isfinite(arr)):
        raise UserError(f"{path}: contains non-finite values")
    values, unknown = map_by_name(arr, header, names, str(path), strict=False)
    notes = [f"{path}: ignored columns this run lacks ({', '.join(unknown)})"] if unknown else []
    return values, notes


STILLS_FPS = 4.0
"""The frame rate of a split whose frames are not a clip's (the built-in scene's
re-animation splits: each frame a new expression from a new camera): at a clip's 30 fps
its 10 frames flashed by in a third of a second."""


def split_fps(ds, frames) -> float | None:
    """The rate a dataset's frames play at: the clip's (`Dataset.frame_rate`; None where it
    stores no times) for capture frames, `STILLS_FPS` for frames outside the capture."""
    return ds.frame_rate() if all(f.in_capture for f in frames) else STILLS_FPS


def from_split(ds, split: str, panel_hw: tuple[int, int] | None = None) -> ExpressionSequence:
    """A dataset split's expressions, cameras, per-frame face meshes and images, at the
    clip's frame rate (`capture`: the clip's frames in order), or `STILLS_FPS` for frames
    outside the capture."""
    frames = ds.split(split)
    if not frames:
        raise UserError(f"{ds.root / 'transforms.json'}: split {split!r} is empty")

    def driving(i: int) -> np.ndarray:
        img = ds.load_image(frames[i])
        if panel_hw is not None:
            h = panel_hw[0]
            img = resize_image(img, max(1, round(img.shape[1] * h / img.shape[0])), h)
        return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)

    return ExpressionSequence(
        ds.expression_matrix(frames), label=split, fps=split_fps(ds, frames),
        cameras=np.stack([f.c2w for f in frames]),
        vertices=ds.face_vertices[[f.position for f in frames]], driving=driving)


MAX_GAIN = 10.0


def parse_gains(items: list[str] | None, names: list[str], where: str = "--gain"
                ) -> dict[str, float]:
    """`name=G[,name=G]` items (a pair's stem sets both sides, as for keyframes) ->
    {control: gain}; a one-line UserError for a name that is no control (or no pair's
    stem) or a gain outside 0..MAX_GAIN."""
    stems = [n[:-4] for n in names if n.endswith("Left") and n[:-4] + "Right" in names]
    out: dict[str, float] = {}
    for item in items or []:
        for name, g in parse_assignments(item, names + stems, where, "control").items():
            if not 0 <= g <= MAX_GAIN:
                raise UserError(f"{where} {item!r}: the gain of {name} must be 0 to "
                                f"{MAX_GAIN:g}")
            out.update({c: g for c in resolve_control(name, names)})
    return out


def from_video(video: Path, ds, names: list[str], relative: bool = True,
               fps: float | None = None, max_frames: int | None = None,
               panel_height: int | None = None, landmarker: Path | None = None,
               match_range: bool = False, gains: dict[str, float] | None = None
               ) -> ExpressionSequence:
    """Track a driving video (`flamenerf track`'s pipeline) -> its expressions, mapped by
    control name onto the run's, and its frames (for side-by-side videos).

    With `relative` and a dataset of the same expression model, expressions are transferred
    relative to each subject's neutral face (as `flamenerf track --relative-to`); with
    `match_range` too, each control's motion is scaled from the driver's reach to the
    subject's (tracking/expressions.range_gains). `gains` {control: g} scale each named
    control's motion from the subject's neutral (from 0 without the relative transfer)."""
    from flamenerf.tracking.expressions import transfer_to_subject
    from flamenerf.tracking.driving import track_expressions

    tr = track_expressions(video, fps=fps, max_frames=max_frames, landmarker=landmarker)
    notes = []
    neutral = None
    if relative and tr.names == ds.expression_names and tr.kind == ds.expression_kind:
        tr = transfer_to_subject(tr, ds, mode="range" if match_range else "relative")
        neutral = np.asarray(tr.transfer["subject_neutral"], np.float32)
        notes.append("expressions transferred relative to each subject's neutral face"
                     + (", each control's reach matched to the subject's" if match_range
                        else ""))
    elif match_range:
        notes.append("--match-range: needs the relative transfer (a dataset of the driver's "
                     "expression model): ignored")
    values, unknown = map_by_name(tr.frames, tr.names, names, str(video), strict=False)
    if gains:
        rest = (np.zeros(len(names), np.float32) if neutral is None or names != tr.names
                else neutral)
        g = np.array([gains.get(n, 1.0) for n in names], np.float32)
        values = (rest + g * (values - rest)).astype(np.float32)
        notes.append("gains " + ", ".join(f"{n} x{v:g}" for n, v in gains.items()))
    if unknown:
        notes.append(f"{video}: {len(unknown)} tracked controls are not in this run's "
                     "expression model and are ignored")
    info = probe_video(video)
    images: dict[int, np.ndarray] = {}
    want = list(tr.source_frames or range(len(values)))
    crop = None
    if tr.face_box is not None and len(tr.face_box) == len(want):
        from flamenerf.tracking.crop import stable_square_crop

        # the driving face, framed as preprocessing frames a subject: one square window for
        # the clip, so that driving and result panels show faces of like size side by side
        opts = ((getattr(ds, "meta", None) or {}).get("source") or {}).get("options") or {}
        scale = opts.get("crop_scale")  # the subject's own framing, when it has one
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not scale > 0:
            scale = 2.0
        crop = stable_square_crop(np.asarray(tr.face_box), info.width, info.height,
                                  panel_height or 512, scale=float(scale))[0]
    for idx, img in iter_frames(info, np.asarray(want)):
        if crop is not None:
            img = crop.apply(img)
        elif panel_height is not None:
            w = max(1, round(img.shape[1] * panel_height / img.shape[0]))
            img = resize_image(img.astype(np.float32) / 255, w, panel_height)
            img = (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
        images[idx] = img
    blank = next(iter(images.values())) * 0 if images else None

    def driving(i: int) -> np.ndarray:
        return images.get(want[i], blank)

    times = None if tr.times is None else np.asarray(tr.times, np.float64)
    return ExpressionSequence(values, label=Path(video).stem, fps=tr.fps, driving=driving,
                              notes=tuple(notes), head_pose=tr.head_pose, times=times)
