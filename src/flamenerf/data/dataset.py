"""The one dataset format, written by `synth` and `preprocess`, read by everything else.

Layout (see docs/dataset_format.md)::

    DATASET/
      transforms.json          cameras, expressions, splits (instant-ngp / nerfstudio style)
      images/000000.png        RGB frames
      masks/000000.png         face-model silhouette = the spatial prior (255 = face)
      depth/000000.npy         optional ground-truth z-depth (float32, metres), synthetic only
      moving/000000.png        optional: background that moves by itself (nonzero = moving:
                               leaves, water, passers-by); training weighs it down
      face_mesh.npz            faces (F, 3) int32; vertices (num_frames, V, 3) float32, world
      expression_model.npz     optional (`preprocess --consistent-expressions`): the β -> mesh
                               model fitted to mean what the tracker means by each control
                               (tracking/expression_model.py)

Conventions: `transform_matrix` is camera-to-world with OpenGL camera axes (x right, y up,
camera looks down -z). Depth is z-depth (distance along the camera's viewing axis), which is
also what the renderer returns because its ray directions have unit -z component.

A frame may carry its rigid head pose `head_pose` (4x4 world-from-head, metres): either every
frame has one or none does; without them the head is the world (the paper's still head).

Every frame of the capture (splits `train` and `val`) has an integer `frame_index` that
selects its deformation and appearance codes. Frames of synthetic-only splits
(`reanimate`, `leakage`) have `frame_index: null`: they are rendered with frame 0's codes.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from flamenerf.errors import UserError, warn
from flamenerf.geometry import is_rigid
from flamenerf.data.face_parts import LANDMARK_KEYS
from flamenerf.data.video import FPS_RANGE
from flamenerf.io import atomic_write_bytes, temp_prefix
from flamenerf.outdir import check_replaceable, clean_stale_temps, replace_dir, writable_dir

FORMAT_VERSION = 1
CAPTURE = "capture"
"""The split every dataset has without storing it: its capture frames (train and val) in
the order of their codes, which is the clip's (`Dataset.split`)."""


class DatasetError(UserError):
    """A dataset file is missing or malformed. The message names the file and the problem."""


@dataclass
class Intrinsics:
    """Pinhole intrinsics in pixels."""

    w: int
    h: int
    fx: float
    fy: float
    cx: float
    cy: float

    def scaled(self, factor: float) -> "Intrinsics":
        """Intrinsics of the same camera at `factor` times the resolution."""
        w, h = max(1, round(self.w * factor)), max(1, round(self.h * factor))
        sx, sy = w / self.w, h / self.h
        return Intrinsics(w, h, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy)

    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], np.float64)


@dataclass
class Frame:
    """One image of the dataset (any split)."""

    position: int  # index into Dataset.frames
    file_path: str
    mask_path: str
    c2w: np.ndarray  # (4, 4) float64, OpenGL axes
    expression: np.ndarray  # (dim_expr,) float32
    frame_index: int | None  # code index; None for frames outside the capture
    depth_path: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    head_pose: np.ndarray | None = None  # (4, 4) float64 world-from-head, or None
    moving_path: str | None = None  # background that moves by itself, or None: not known

    @property
    def paths(self) -> tuple[str, ...]:
        """The frame's files, relative to the dataset's folder: image, mask and, where it
        has them, depth and moving-background mask."""
        return tuple(p for p in (self.file_path, self.mask_path, self.depth_path,
                                 self.moving_path) if p is not None)

    @property
    def in_capture(self) -> bool:
        """Whether the frame is one of the filmed clip's (it has codes of its own); the
        built-in scene's re-animation splits' frames are not."""
        return self.frame_index is not None


GAP = 1.75
"""A step between consecutive frames longer than this many times the clip's median step
is a gap (frames the camera dropped, or where no face was found): it plays for its time."""


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


def frame_times(frames: list[Frame]) -> np.ndarray | None:
    """(n,) the frames' `time`s in seconds (`preprocess` stores them), or None where a frame
    has none (the built-in scene's)."""
    times = [f.extra.get("time") for f in frames]
    if times and all(isinstance(t, (int, float)) for t in times):
        return np.asarray(times, np.float64)
    return None


def frames_shown(frames: list[Frame], fps: float) -> np.ndarray | None:
    """(n,) how many ticks of 1 / `fps` each of a clip's `frames` (in order) stays on screen
    as they play in the time they took (`playback`: the frame before a gap held for the
    gap's time); None where each is shown once (no gap, or no times stored)."""
    times = frame_times(frames)
    plan = None if times is None else playback(times, fps)
    return None if plan is None or (plan[1] == 1).all() else plan[1]


def frame_rate(frames: list[Frame]) -> float | None:
    """Frames per second of frames in clip order (`playback`'s rate: that of the steps that
    are no gap); None where a frame stores no time (the built-in scene's)."""
    times = frame_times(frames)
    plan = None if times is None else playback(times)
    return None if plan is None else plan[0]


@dataclass
class Dataset:
    root: Path
    intrinsics: Intrinsics
    near: float
    far: float
    expression_kind: str
    expression_names: list[str]
    splits: dict[str, list[int]]  # split name -> positions into `frames`
    frames: list[Frame]
    faces: np.ndarray  # (F, 3) int32
    face_vertices: np.ndarray  # (num_frames, V, 3) float32, world coordinates
    source: dict[str, Any]
    meta: dict[str, Any]  # the whole transforms.json, for fields not modelled above
    face_landmarks: dict[str, list[int]] | None = None
    """Vertex indices of the eyes and the mouth on the face mesh (`eye_left`, `eye_right`,
    `mouth`) where the mesh is not MediaPipe's (data/face_parts.py)."""
    mesh_model: "StoredMeshModel | None" = None
    """The β -> mesh model stored with the dataset (`expression_model.npz`), or None."""

    @property
    def expression_dim(self) -> int:
        return len(self.expression_names)

    @property
    def has_head_poses(self) -> bool:
        """Whether the frames carry rigid head poses (all of them do, or none)."""
        return self.frames[0].head_pose is not None

    @property
    def num_codes(self) -> int:
        """Size of the per-frame code tables (deformation ω, appearance φ)."""
        idx = [f.frame_index for f in self.frames if f.in_capture]
        return (max(idx) + 1) if idx else 1

    def capture(self) -> list[Frame]:
        """Every capture frame (one with a frame index: train and val) in the order of its
        code, which is the clip's; [] for a dataset of none."""
        return sorted((f for f in self.frames if f.in_capture),
                      key=lambda f: f.frame_index)

    def split(self, name: str) -> list[Frame]:
        """A stored split's frames, or for `capture` (unless stored) `capture()`: the clip
        as filmed."""
        capture = self.capture() if name == CAPTURE and name not in self.splits else []
        if capture:
            return capture
        if name not in self.splits:
            have = sorted(self.splits) + ([CAPTURE] if self.capture() else [])
            raise DatasetError(
                f"{self.root / 'transforms.json'}: no split named {name!r} "
                f"(have: {', '.join(have)})"
            )
        return [self.frames[i] for i in self.splits[name]]

    def frame_rate(self) -> float | None:
        """The clip's frames per second (`frame_rate` of the capture), for any of its
        splits' videos; None where the frames store no times."""
        return frame_rate(self.capture())

    def training_frames(self) -> list[Frame]:
        """The frames a model of this dataset learns from: the `train` split, or every
        capture frame when there is none."""
        train = self.split("train") if "train" in self.splits else []
        return train or self.capture()

    def load_image(self, frame: Frame) -> np.ndarray:
        """(H, W, 3) float32 in [0, 1]."""
        path = self.root / frame.file_path
        img = _read_png(path, self.intrinsics)
        if img.ndim == 2:
            img = img[..., None]
        # 8- or 16-bit integers (a 16-bit PNG read as 8-bit would train on garbage)
        top = np.iinfo(img.dtype).max if np.issubdtype(img.dtype, np.integer) else 1.0
        img = img.astype(np.float32) / np.float32(top)
        if img.shape[-1] in (2, 4):  # grey or RGB with alpha
            # what a cut-out hides is often leftover colour: over black it is nothing
            if self.root not in _ALPHA_NOTED:
                _ALPHA_NOTED.add(self.root)
                warn(f"{path}: has an alpha channel; frames are composited over black")
            img = img[..., :-1] * img[..., -1:]
        return np.repeat(img, 3, axis=-1) if img.shape[-1] == 1 else img[..., :3]

    def load_mask(self, frame: Frame) -> np.ndarray:
        """(H, W) bool, True on the face-model silhouette."""
        m = _read_png(self.root / frame.mask_path, self.intrinsics)
        if m.ndim == 3:
            m = m[..., 0]
        return m > 127

    def load_depth(self, frame: Frame) -> np.ndarray | None:
        """(H, W) float32 z-depth, or None when the dataset has no ground-truth depth."""
        if frame.depth_path is None:
            return None
        path = self.root / frame.depth_path
        try:
            d = np.load(path, allow_pickle=False)  # a .npy of objects could run code
        except FileNotFoundError:
            raise DatasetError(f"{path}: file is missing") from None
        except Exception as e:  # noqa: BLE001 - any parse failure is the file's fault
            raise DatasetError(f"{path}: not a readable .npy depth map ({e})") from None
        if d.shape != (self.intrinsics.h, self.intrinsics.w):
            raise DatasetError(
                f"{path}: depth has shape {d.shape}, expected "
                f"{(self.intrinsics.h, self.intrinsics.w)}"
            )
        return d.astype(np.float32)

    def load_moving(self, frame: Frame) -> np.ndarray | None:
        """(H, W) bool, True on background that moves by itself (nonzero in the stored
        mask), or None when the frame has no such mask (nothing is known to move)."""
        if frame.moving_path is None:
            return None
        m = _read_png(self.root / frame.moving_path, self.intrinsics)
        if m.ndim == 3:
            m = m[..., 0]
        return m > 0

    @property
    def has_moving(self) -> bool:
        """Whether any frame carries a moving-background mask."""
        return any(f.moving_path is not None for f in self.frames)

    def expression_matrix(self, frames: list[Frame]) -> np.ndarray:
        """(len(frames), dim_expr) float32."""
        return np.stack([f.expression for f in frames]).astype(np.float32)


@dataclass
class StoredMeshModel:
    """A β -> mesh model kept with the dataset (`expression_model.npz`): neutral (V, 3) and
    basis (E, V, 3) float32 in the canonical frame, fitted with `ridge` and each control on
    its part of the face; `method` says how (tracking/expression_model.py)."""

    neutral: np.ndarray
    basis: np.ndarray
    ridge: float
    method: str


MESH_MODEL_FILE = "expression_model.npz"


def write_mesh_model(root: str | os.PathLike, model: StoredMeshModel) -> Path:
    """Store a β -> mesh model in a dataset (atomically; read back by `load_dataset`)."""
    path = Path(root) / MESH_MODEL_FILE
    atomic_write_bytes(path, lambda f: np.savez(
        f, neutral=model.neutral.astype(np.float32), basis=model.basis.astype(np.float32),
        ridge=np.float64(model.ridge), method=np.str_(model.method)))
    return path


def _read_mesh_model(path: Path, num_vertices: int, dim: int) -> StoredMeshModel | None:
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            m = StoredMeshModel(z["neutral"].astype(np.float32), z["basis"].astype(np.float32),
                                float(z["ridge"]), str(z["method"]))
    except KeyError as e:
        raise DatasetError(f"{path}: missing array {e}") from None
    except Exception as e:  # noqa: BLE001
        raise DatasetError(f"{path}: not a readable .npz ({type(e).__name__})") from None
    if m.neutral.shape != (num_vertices, 3) or m.basis.shape != (dim, num_vertices, 3):
        raise DatasetError(f"{path}: expected neutral ({num_vertices}, 3) and basis ({dim}, "
                           f"{num_vertices}, 3), got {m.neutral.shape} and {m.basis.shape}")
    if not (np.isfinite(m.neutral).all() and np.isfinite(m.basis).all()):
        raise DatasetError(f"{path}: holds non-finite values")
    return m


def reference_position(ds: Dataset) -> int:
    """Position (in ds.frames) of frame 0: the frame whose codes re-animation, the viewer
    and the spatial prior's default mask use."""
    for f in ds.frames:
        if f.frame_index == 0:
            return f.position
    return ds.splits["train"][0]


_ALPHA_NOTED: set[Path] = set()  # datasets whose alpha was announced (once each)


def _read_png(path: Path, intr: Intrinsics) -> np.ndarray:
    import imageio.v3 as iio

    if not path.exists():
        raise DatasetError(f"{path}: file is missing")
    try:
        img = iio.imread(path)
    except Exception as e:  # noqa: BLE001
        raise DatasetError(f"{path}: not a readable image ({type(e).__name__})") from None
    if img.shape[:2] != (intr.h, intr.w):
        raise DatasetError(
            f"{path}: image is {img.shape[1]}x{img.shape[0]}, transforms.json says "
            f"{intr.w}x{intr.h}"
        )
    return img


# ----------------------------------------------------------------------------- reading


def _require(obj: dict, key: str, where: str, kinds: type | tuple[type, ...]) -> Any:
    if key not in obj:
        raise DatasetError(f"{where}: missing field {key!r}")
    val = obj[key]
    if not isinstance(val, kinds) or (isinstance(val, bool) and kinds is not bool):
        raise DatasetError(f"{where}: field {key!r} has the wrong type ({type(val).__name__})")
    return val


def _optional(obj: dict, key: str, where: str, kinds: type | tuple[type, ...]) -> Any:
    """obj[key] when present and not null (checked as `_require` checks), else None."""
    return None if obj.get(key) is None else _require(obj, key, where, kinds)


def _numbers(values: list, dtype) -> np.ndarray | None:
    """A JSON list as an array, or None when it holds non-numbers or rows of unequal
    length (numpy would raise, or make an object array of strings)."""
    if any(isinstance(v, (str, bool, dict)) or v is None for v in _flat(values)):
        return None
    try:
        return np.asarray(values, dtype=dtype)
    except (ValueError, TypeError):
        return None


def _flat(values):
    for v in values:
        if isinstance(v, list):
            yield from _flat(v)
        else:
            yield v


HEAD_POSE_TOL = 1e-4  # how far a head pose's rotation may be from orthonormal
CAMERA_TOL = 1e-3  # ... and a camera's (files written by other tools in single precision)
# Beyond these a value is a broken file, not a scene: positions and depths are metres, a
# control is about 0..1 (blendshapes) or a few units (FLAME), and a focal length a thousand
# image widths is a 0.06-degree view. (1e30 trained silently on garbage; 1e308 overflowed.)
MAX_METRES = 1e4
MAX_CONTROL = 1e3
MAX_FOCAL_WIDTHS = 1e3
MAX_SIZE = 4096  # pixels a side that `synth` and `preprocess` make frames of


def _face_landmarks(meta: dict, where: str, num_vertices: int) -> dict[str, list[int]] | None:
    """The optional `face_landmarks`, checked: each of the keys a non-empty list of vertex
    indices of the face mesh."""
    raw = meta.get("face_landmarks")
    if raw is None:
        return None
    if not isinstance(raw, dict):
        raise DatasetError(f"{where}: face_landmarks must be an object")
    out = {}
    for k in LANDMARK_KEYS:
        idx = raw.get(k)
        if (not isinstance(idx, list) or not idx
                or not all(isinstance(i, int) and 0 <= i < num_vertices for i in idx)):
            raise DatasetError(f"{where}: face_landmarks.{k} must list vertex indices of "
                               f"the face mesh (in [0, {num_vertices}))")
        out[k] = idx
    return out


def _head_pose(fr: dict, w: str) -> np.ndarray | None:
    """A frame's optional `head_pose`, validated: a finite rigid 4x4 (rotation with det +1,
    last row 0 0 0 1)."""
    if "head_pose" not in fr or fr["head_pose"] is None:
        return None
    raw = fr["head_pose"]
    m = _numbers(raw, np.float64) if isinstance(raw, list) else None
    if m is None or m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise DatasetError(f"{w}: head_pose must be a finite 4x4 matrix of numbers")
    if not is_rigid(m, HEAD_POSE_TOL):
        raise DatasetError(f"{w}: head_pose must be rigid (a rotation, a translation and a "
                           "last row 0 0 0 1)")
    _check_position(m, w, "head_pose")
    return m


def too_far(m: np.ndarray) -> np.ndarray:
    """Whether poses m (..., 4, 4) put their origin more than MAX_METRES (along an axis) from
    the world's: a broken file, not a scene. -> (...) bool."""
    return np.abs(m[..., :3, 3]).max(-1) > MAX_METRES


def _check_position(m: np.ndarray, w: str, field: str) -> None:
    if too_far(m):
        raise DatasetError(f"{w}: {field} puts it {np.abs(m[:3, 3]).max():.3g} m from the "
                           f"origin (more than {MAX_METRES:g} m: positions are metres)")


def load_dataset(root: str | os.PathLike, check_files: bool = True) -> Dataset:
    """Read and validate a dataset; any problem becomes one DatasetError naming the file."""
    root = Path(root)
    tj = root / "transforms.json"
    if root.exists() and not root.is_dir():
        raise DatasetError(f"{root}: is a file; give the dataset directory (the folder "
                           "holding transforms.json)")
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset directory does not exist")
    if not tj.exists():
        raise DatasetError(f"{tj}: file is missing (is {root} a flamenerf dataset?)")
    try:
        meta = json.loads(tj.read_text())
    except json.JSONDecodeError as e:
        raise DatasetError(f"{tj}: invalid JSON at line {e.lineno} ({e.msg})") from None
    except RecursionError:
        raise DatasetError(f"{tj}: not valid JSON here (nested too deeply to read)") from None
    if not isinstance(meta, dict):
        raise DatasetError(f"{tj}: top level must be a JSON object")
    where = str(tj)
    version = meta.get("format_version", FORMAT_VERSION)
    if not isinstance(version, int) or isinstance(version, bool):
        raise DatasetError(f"{where}: format_version {version!r} is not a version number")
    if version > FORMAT_VERSION:
        raise DatasetError(f"{where}: format_version {version!r} is newer than this "
                           f"flamenerf reads ({FORMAT_VERSION}); update flamenerf")
    model = meta.get("camera_model", "OPENGL_PINHOLE")
    if not isinstance(model, str) or not model.upper().endswith("PINHOLE"):
        raise DatasetError(f"{where}: camera_model {model!r}: flamenerf reads pinhole cameras "
                           "only (undistort the frames first)")
    if not isinstance(meta.get("prior", {}), dict):
        raise DatasetError(f"{where}: 'prior' must be an object (e.g. {{\"dilation_px\": 1}})")
    num = (int, float)
    intr = Intrinsics(
        w=int(_require(meta, "w", where, int)),
        h=int(_require(meta, "h", where, int)),
        fx=float(_require(meta, "fl_x", where, num)),
        fy=float(_require(meta, "fl_y", where, num)),
        cx=float(_require(meta, "cx", where, num)),
        cy=float(_require(meta, "cy", where, num)),
    )
    if intr.w <= 0 or intr.h <= 0:
        raise DatasetError(f"{where}: image size w={intr.w}, h={intr.h} must be positive")
    if not (np.isfinite([intr.fx, intr.fy]).all() and intr.fx > 0 and intr.fy > 0):
        raise DatasetError(f"{where}: focal lengths fl_x={intr.fx}, fl_y={intr.fy} must be "
                           "positive")
    if max(intr.fx / intr.w, intr.fy / intr.h) > MAX_FOCAL_WIDTHS:
        raise DatasetError(f"{where}: focal lengths fl_x={intr.fx:.3g}, fl_y={intr.fy:.3g} are "
                           f"more than {MAX_FOCAL_WIDTHS:g} times the image size")
    if not np.isfinite([intr.cx, intr.cy]).all():
        raise DatasetError(f"{where}: principal point cx={intr.cx}, cy={intr.cy} must be finite")
    near = float(_require(meta, "near", where, num))
    far = float(_require(meta, "far", where, num))
    if not (0 <= near < far <= MAX_METRES):
        raise DatasetError(f"{where}: need 0 <= near < far <= {MAX_METRES:g} (metres), got "
                           f"near={near:g}, far={far:g}")
    em = _require(meta, "expression_model", where, dict)
    names = _require(em, "names", f"{where} expression_model", list)
    kind = str(em.get("kind", "unknown"))
    dim = len(names)
    if em.get("dim", dim) != dim:  # one of them was edited: which the frames follow is a guess
        raise DatasetError(f"{where}: expression_model dim {em['dim']!r} but {dim} names")
    raw_frames = _require(meta, "frames", where, list)
    if not raw_frames:
        raise DatasetError(f"{where}: 'frames' is empty")
    frames = []
    for i, fr in enumerate(raw_frames):
        w = f"{where} frames[{i}]"
        if not isinstance(fr, dict):
            raise DatasetError(f"{w}: must be an object")
        c2w = _numbers(_require(fr, "transform_matrix", w, list), np.float64)
        if c2w is None or c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
            raise DatasetError(f"{w}: transform_matrix must be a finite 4x4 matrix of numbers")
        if not is_rigid(c2w, CAMERA_TOL):
            raise DatasetError(f"{w}: transform_matrix must be rigid (a rotation, a "
                               "translation and a last row 0 0 0 1)")
        _check_position(c2w, w, "transform_matrix")
        # read in double: a float32 cast would turn 1e308 into inf with a numpy warning
        expr = _numbers(_require(fr, "expression", w, list), np.float64)
        if expr is None:
            raise DatasetError(f"{w}: expression must be a flat list of numbers")
        if expr.shape != (dim,):
            raise DatasetError(
                f"{w}: expression has {expr.size} values, expression_model names {dim}"
            )
        if not np.all(np.isfinite(expr)):
            raise DatasetError(f"{w}: expression holds a value that is not a finite number")
        if np.abs(expr).max(initial=0) > MAX_CONTROL:
            raise DatasetError(f"{w}: expression holds {expr[np.abs(expr).argmax()]:.3g}, "
                               f"beyond the +-{MAX_CONTROL:g} any control is taken to mean")
        expr = expr.astype(np.float32)
        fi = fr.get("frame_index")
        if fi is not None and (not isinstance(fi, int) or fi < 0):
            raise DatasetError(f"{w}: frame_index must be a non-negative integer or null")
        if fi is not None and fi >= len(raw_frames):  # it sizes the per-frame code tables
            raise DatasetError(f"{w}: frame_index {fi} must be below the number of frames "
                               f"({len(raw_frames)})")
        known = {"file_path", "mask_path", "depth_path", "moving_path", "transform_matrix",
                 "expression", "frame_index", "head_pose"}
        frames.append(
            Frame(
                position=i,
                file_path=str(_require(fr, "file_path", w, str)),
                mask_path=str(_require(fr, "mask_path", w, str)),
                c2w=c2w,
                expression=expr,
                frame_index=fi,
                depth_path=_optional(fr, "depth_path", w, str),
                extra={k: v for k, v in fr.items() if k not in known},
                head_pose=_head_pose(fr, w),
                moving_path=_optional(fr, "moving_path", w, str),
            )
        )
    posed = [f.head_pose is not None for f in frames]
    if any(posed) and not all(posed):
        raise DatasetError(f"{where}: frames[{posed.index(not posed[0])}] "
                           f"{'lacks' if posed[0] else 'has'} a head_pose that frames[0] "
                           f"{'has' if posed[0] else 'lacks'} (give every frame one, or none)")
    splits_raw = _require(meta, "splits", where, dict)
    splits: dict[str, list[int]] = {}
    for name, idx in splits_raw.items():
        if not isinstance(idx, list) or not all(
            isinstance(j, int) and 0 <= j < len(frames) for j in idx
        ):
            raise DatasetError(
                f"{where}: split {name!r} must list frame positions in [0, {len(frames)})"
            )
        splits[name] = idx
    if "train" not in splits or not splits["train"]:
        raise DatasetError(f"{where}: needs a non-empty 'train' split")
    for name in ("train", "val"):
        for j in splits.get(name, []):
            if frames[j].frame_index is None:
                raise DatasetError(f"{where}: frame {j} of split {name!r} has no frame_index")

    mesh_path = root / "face_mesh.npz"
    if not mesh_path.exists():
        raise DatasetError(f"{mesh_path}: file is missing")
    try:
        with np.load(mesh_path, allow_pickle=False) as z:
            faces = z["faces"].astype(np.int32)
            with np.errstate(over="ignore", invalid="ignore"):  # too large: refused below
                verts = z["vertices"].astype(np.float32)
    except KeyError as e:
        raise DatasetError(f"{mesh_path}: missing array {e}") from None
    except Exception as e:  # noqa: BLE001
        raise DatasetError(f"{mesh_path}: not a readable .npz ({type(e).__name__})") from None
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise DatasetError(f"{mesh_path}: 'faces' must have shape (F, 3) with F > 0, got "
                           f"{faces.shape}")
    if verts.ndim != 3 or verts.shape[0] != len(frames) or verts.shape[2] != 3:
        raise DatasetError(
            f"{mesh_path}: 'vertices' must have shape ({len(frames)}, V, 3), got {verts.shape}"
        )
    if faces.size and (faces.min() < 0 or faces.max() >= verts.shape[1]):
        raise DatasetError(f"{mesh_path}: 'faces' index vertices out of range")
    if not (np.isfinite(verts).all() and np.abs(verts).max(initial=0) <= MAX_METRES):
        raise DatasetError(f"{mesh_path}: 'vertices' must be finite and within {MAX_METRES:g} m "
                           "of the origin")

    landmarks = _face_landmarks(meta, where, verts.shape[1])
    ds = Dataset(
        root=root,
        intrinsics=intr,
        near=near,
        far=far,
        expression_kind=kind,
        expression_names=[str(n) for n in names],
        splits=splits,
        frames=frames,
        faces=faces,
        face_vertices=verts,
        source=meta.get("source", {}),
        meta=meta,
        face_landmarks=landmarks,
        mesh_model=_read_mesh_model(root / MESH_MODEL_FILE, verts.shape[1], len(names)),
    )
    for fr in frames:
        for rel in fr.paths:
            # a dataset reads only its own files, not whatever path it names
            if Path(rel).is_absolute() or ".." in Path(rel).parts:
                raise DatasetError(f"{tj}: frames[{fr.position}]: {rel!r} is outside the "
                                   "dataset (paths are relative to its folder)")
            if check_files and not (root / rel).exists():
                raise DatasetError(f"{root / rel}: file is missing")
    return ds


def fingerprint(ds: Dataset) -> str:
    """A hash of what a dataset holds, wherever it lies: transforms.json's bytes and each
    frame's image, mask, depth and moving-background files by name and size (not their
    pixels: hashing every image would cost a resume seconds on a long clip, and a dataset
    made again changes transforms.json). What a run records to tell on --resume that it is
    its dataset."""
    h = hashlib.sha256((ds.root / "transforms.json").read_bytes())
    for fr in ds.frames:
        for rel in fr.paths:
            p = ds.root / rel
            h.update(f"\0{rel}\0{p.stat().st_size if p.exists() else -1}".encode())
    return "sha256:" + h.hexdigest()


# ----------------------------------------------------------------------------- writing


class DatasetWriter:
    """Writes a dataset into a temporary sibling directory and renames it into place on
    `close()`, so an interrupted run never leaves a half-written dataset behind.

    Usage::

        with DatasetWriter(out, intrinsics, near, far, names, kind="synthetic") as w:
            w.add_frame(rgb, mask, c2w, expr, frame_index, split="train", depth=d, verts=v)
            w.set_faces(faces)
    """

    def __init__(
        self,
        out: str | os.PathLike,
        intrinsics: Intrinsics,
        near: float,
        far: float,
        expression_names: list[str],
        expression_kind: str,
        expression_info: dict[str, Any] | None = None,
        source: dict[str, Any] | None = None,
        overwrite: bool = False,
        prior_dilation_px: int | None = None,
    ):
        self.out = Path(out)
        if self.out.exists() and not overwrite:
            raise DatasetError(f"{self.out}: already exists (pass --overwrite to replace it)")
        check_replaceable(self.out, "dataset")
        writable_dir(self.out.parent, "dataset")
        clean_stale_temps(self.out.parent, re.escape(self.out.name))  # a killed writer's
        self.tmp = Path(tempfile.mkdtemp(prefix=temp_prefix(self.out.name), dir=self.out.parent))
        os.chmod(self.tmp, 0o755)  # mkdtemp makes 0700; a dataset is an ordinary folder
        for sub in ("images", "masks"):
            (self.tmp / sub).mkdir()
        self.intr = intrinsics
        self.meta: dict[str, Any] = {
            "format_version": FORMAT_VERSION,
            "w": intrinsics.w,
            "h": intrinsics.h,
            "fl_x": intrinsics.fx,
            "fl_y": intrinsics.fy,
            "cx": intrinsics.cx,
            "cy": intrinsics.cy,
            "camera_model": "OPENGL_PINHOLE",
            "near": float(near),
            "far": float(far),
            "expression_model": {
                "kind": expression_kind,
                "dim": len(expression_names),
                "names": list(expression_names),
                **(expression_info or {}),
            },
            "source": source or {},
            # the dilation of the silhouette masks (data/prior.py makes every other mask
            # the same way from it)
            **({} if prior_dilation_px is None else
               {"prior": {"dilation_px": int(prior_dilation_px)}}),
            "splits": {},
            "frames": [],
        }
        self.faces: np.ndarray | None = None
        self.verts: list[np.ndarray] = []
        self.overwrite = overwrite

    def add_frame(
        self,
        rgb: np.ndarray,
        mask: np.ndarray,
        c2w: np.ndarray,
        expression: np.ndarray,
        frame_index: int | None,
        split: str,
        verts: np.ndarray,
        depth: np.ndarray | None = None,
        extra: dict[str, Any] | None = None,
        head_pose: np.ndarray | None = None,
        moving: np.ndarray | None = None,
    ) -> int:
        """Add one frame. rgb (H, W, 3) uint8 or float in [0, 1]; mask (H, W) bool;
        verts (V, 3) world-space face-mesh vertices; head_pose (4, 4) world-from-head or
        None (give it for every frame or for none); moving (H, W) bool (or any array:
        nonzero = background that moves by itself) or None. A given `moving` is written
        even where nothing in it is set, so that "looked, none moves" is recorded apart
        from "not known" (None: no `moving_path`). Returns the frame's position."""
        import imageio.v3 as iio

        pos = len(self.meta["frames"])
        name = f"{pos:06d}"
        if rgb.dtype != np.uint8:
            rgb = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
        iio.imwrite(self.tmp / "images" / f"{name}.png", rgb[..., :3])
        iio.imwrite(self.tmp / "masks" / f"{name}.png", (mask > 0).astype(np.uint8) * 255)
        entry: dict[str, Any] = {
            "file_path": f"images/{name}.png",
            "mask_path": f"masks/{name}.png",
            "transform_matrix": np.asarray(c2w, np.float64).tolist(),
            "expression": [float(x) for x in np.asarray(expression).ravel()],
            "frame_index": None if frame_index is None else int(frame_index),
        }
        if depth is not None:
            (self.tmp / "depth").mkdir(exist_ok=True)
            np.save(self.tmp / "depth" / f"{name}.npy", depth.astype(np.float32))
            entry["depth_path"] = f"depth/{name}.npy"
        if moving is not None:
            entry["moving_path"] = self._write_moving(name, moving, rgb.shape[:2])
        if extra:
            entry.update(extra)
        if head_pose is not None:
            entry["head_pose"] = np.asarray(head_pose, np.float64).tolist()
        self.meta["frames"].append(entry)
        self.meta["splits"].setdefault(split, []).append(pos)
        self.verts.append(np.asarray(verts, np.float32))
        return pos

    def _write_moving(self, name: str, moving: np.ndarray, size: tuple[int, int]) -> str:
        """Store a frame's moving-background mask (H, W) as a 0/255 PNG -> its path."""
        import imageio.v3 as iio

        moving = np.asarray(moving)
        if moving.shape != tuple(size):
            raise ValueError(f"moving mask has shape {moving.shape}, the frame is {size}")
        (self.tmp / "moving").mkdir(exist_ok=True)
        iio.imwrite(self.tmp / "moving" / f"{name}.png", (moving != 0).astype(np.uint8) * 255)
        return f"moving/{name}.png"

    def set_faces(self, faces: np.ndarray) -> None:
        self.faces = np.asarray(faces, np.int32)

    def set_meta(self, key: str, value: Any) -> None:
        self.meta[key] = value

    def close(self) -> Path:
        if self.faces is None:
            raise DatasetError(f"{self.out}: no face-mesh triangles set before close()")
        np.savez_compressed(
            self.tmp / "face_mesh.npz", faces=self.faces, vertices=np.stack(self.verts)
        )
        (self.tmp / "transforms.json").write_text(json.dumps(self.meta, indent=1))

        replace_dir(self.tmp, self.out, "dataset")
        return self.out

    def abort(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)

    def __enter__(self) -> "DatasetWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
