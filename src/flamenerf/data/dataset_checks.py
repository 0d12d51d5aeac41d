"""The checks `load_dataset` makes of a dataset's files before anything trusts them
(transforms.json, face_mesh.npz, expression_model.npz): each problem is one DatasetError
that names the file and what is wrong, instead of a traceback or a silent run on garbage.

They hand back plain values (numbers, arrays, dicts) and data/dataset.py builds the format's
objects from them, so that this module needs nothing of the format's classes (dataset.py
imports it)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from flamenerf.data.face_parts import LANDMARK_KEYS
from flamenerf.errors import UserError
from flamenerf.geometry import is_rigid


class DatasetError(UserError):
    """A dataset file is missing or malformed. The message names the file and the problem."""


HEAD_POSE_TOL = 1e-4  # how far a head pose's rotation may be from orthonormal
CAMERA_TOL = 1e-3  # ... and a camera's (files written by other tools in single precision)
# Beyond these a value is a broken file, not a scene: positions and depths are metres, a
# control is about 0..1 (blendshapes) or a few units (FLAME), and a focal length a thousand
# image widths is a 0.06-degree view. (1e30 trained silently on garbage; 1e308 overflowed.)
MAX_METRES = 1e4
MAX_CONTROL = 1e3
MAX_FOCAL_WIDTHS = 1e3

FRAME_FIELDS = {"file_path", "mask_path", "depth_path", "moving_path", "transform_matrix",
                "expression", "frame_index", "head_pose"}
"""A frame's fields the format models; any other is kept in `Frame.extra`."""


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


def too_far(m: np.ndarray) -> np.ndarray:
    """Whether poses m (..., 4, 4) put their origin more than MAX_METRES (along an axis) from
    the world's: a broken file, not a scene. -> (...) bool."""
    return np.abs(m[..., :3, 3]).max(-1) > MAX_METRES


def _check_position(m: np.ndarray, w: str, field: str) -> None:
    if too_far(m):
        raise DatasetError(f"{w}: {field} puts it {np.abs(m[:3, 3]).max():.3g} m from the "
                           f"origin (more than {MAX_METRES:g} m: positions are metres)")


def read_transforms(root: Path) -> dict:
    """The dataset folder's transforms.json, parsed: a JSON object."""
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
    return meta


def check_header(meta: dict, where: str, newest: int) -> None:
    """What flamenerf must know before reading on: a format_version no newer than `newest`
    (the one it writes), pinhole cameras, and a `prior` that is an object."""
    version = meta.get("format_version", newest)
    if not isinstance(version, int) or isinstance(version, bool):
        raise DatasetError(f"{where}: format_version {version!r} is not a version number")
    if version > newest:
        raise DatasetError(f"{where}: format_version {version!r} is newer than this "
                           f"flamenerf reads ({newest}); update flamenerf")
    model = meta.get("camera_model", "OPENGL_PINHOLE")
    if not isinstance(model, str) or not model.upper().endswith("PINHOLE"):
        raise DatasetError(f"{where}: camera_model {model!r}: flamenerf reads pinhole cameras "
                           "only (undistort the frames first)")
    if not isinstance(meta.get("prior", {}), dict):
        raise DatasetError(f"{where}: 'prior' must be an object (e.g. {{\"dilation_px\": 1}})")


def intrinsics_fields(meta: dict, where: str) -> tuple[int, int, float, float, float, float]:
    """The camera's w, h, fl_x, fl_y, cx, cy: a positive size, positive focal lengths no
    longer than MAX_FOCAL_WIDTHS image sizes, a finite principal point."""
    num = (int, float)
    w = int(_require(meta, "w", where, int))
    h = int(_require(meta, "h", where, int))
    fx = float(_require(meta, "fl_x", where, num))
    fy = float(_require(meta, "fl_y", where, num))
    cx = float(_require(meta, "cx", where, num))
    cy = float(_require(meta, "cy", where, num))
    if w <= 0 or h <= 0:
        raise DatasetError(f"{where}: image size w={w}, h={h} must be positive")
    if not (np.isfinite([fx, fy]).all() and fx > 0 and fy > 0):
        raise DatasetError(f"{where}: focal lengths fl_x={fx}, fl_y={fy} must be "
                           "positive")
    if max(fx / w, fy / h) > MAX_FOCAL_WIDTHS:
        raise DatasetError(f"{where}: focal lengths fl_x={fx:.3g}, fl_y={fy:.3g} are "
                           f"more than {MAX_FOCAL_WIDTHS:g} times the image size")
    if not np.isfinite([cx, cy]).all():
        raise DatasetError(f"{where}: principal point cx={cx}, cy={cy} must be finite")
    return w, h, fx, fy, cx, cy


def near_far(meta: dict, where: str) -> tuple[float, float]:
    near = float(_require(meta, "near", where, (int, float)))
    far = float(_require(meta, "far", where, (int, float)))
    if not (0 <= near < far <= MAX_METRES):
        raise DatasetError(f"{where}: need 0 <= near < far <= {MAX_METRES:g} (metres), got "
                           f"near={near:g}, far={far:g}")
    return near, far


def expression_model(meta: dict, where: str) -> tuple[str, list]:
    """The expression model's kind and control names."""
    em = _require(meta, "expression_model", where, dict)
    names = _require(em, "names", f"{where} expression_model", list)
    kind = str(em.get("kind", "unknown"))
    dim = len(names)
    if em.get("dim", dim) != dim:  # one of them was edited: which the frames follow is a guess
        raise DatasetError(f"{where}: expression_model dim {em['dim']!r} but {dim} names")
    return kind, names


def raw_frames(meta: dict, where: str) -> list:
    """transforms.json's `frames`: a non-empty list."""
    frames = _require(meta, "frames", where, list)
    if not frames:
        raise DatasetError(f"{where}: 'frames' is empty")
    return frames


def frame_fields(fr: Any, w: str, dim: int, num_frames: int) -> dict[str, Any]:
    """One entry of `frames` (`w` names it in messages), checked -> the keyword arguments of
    its `Frame` but its position: a finite rigid camera within MAX_METRES, `dim` finite
    controls within MAX_CONTROL, a frame index below `num_frames` (it sizes the code
    tables) or null, the paths, the optional head pose, the fields not modelled (`extra`)."""
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
    if fi is not None and fi >= num_frames:  # it sizes the per-frame code tables
        raise DatasetError(f"{w}: frame_index {fi} must be below the number of frames "
                           f"({num_frames})")
    # in the order the messages of a frame with several problems have always come in
    return dict(
        file_path=str(_require(fr, "file_path", w, str)),
        mask_path=str(_require(fr, "mask_path", w, str)),
        c2w=c2w,
        expression=expr,
        frame_index=fi,
        depth_path=_optional(fr, "depth_path", w, str),
        extra={k: v for k, v in fr.items() if k not in FRAME_FIELDS},
        head_pose=_head_pose(fr, w),
        moving_path=_optional(fr, "moving_path", w, str),
    )


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


def check_head_poses(posed: list[bool], where: str) -> None:
    """Every frame has a head pose (`posed`, in frame order), or none does."""
    if any(posed) and not all(posed):
        raise DatasetError(f"{where}: frames[{posed.index(not posed[0])}] "
                           f"{'lacks' if posed[0] else 'has'} a head_pose that frames[0] "
                           f"{'has' if posed[0] else 'lacks'} (give every frame one, or none)")


def splits(meta: dict, where: str, frame_indices: list[int | None]) -> dict[str, list[int]]:
    """The `splits`: each a list of frame positions (`frame_indices` holds each frame's
    index, in order), a non-empty `train`, and frame indices for every frame of `train` and
    `val` (their codes are trained)."""
    splits_raw = _require(meta, "splits", where, dict)
    out: dict[str, list[int]] = {}
    for name, idx in splits_raw.items():
        if not isinstance(idx, list) or not all(
            isinstance(j, int) and 0 <= j < len(frame_indices) for j in idx
        ):
            raise DatasetError(
                f"{where}: split {name!r} must list frame positions in [0, "
                f"{len(frame_indices)})"
            )
        out[name] = idx
    if "train" not in out or not out["train"]:
        raise DatasetError(f"{where}: needs a non-empty 'train' split")
    for name in ("train", "val"):
        for j in out.get(name, []):
            if frame_indices[j] is None:
                raise DatasetError(f"{where}: frame {j} of split {name!r} has no frame_index")
    return out


def read_face_mesh(mesh_path: Path, num_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """face_mesh.npz -> faces (F, 3) int32 indexing the vertices, vertices (num_frames, V, 3)
    float32, finite and within MAX_METRES of the origin."""
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
    if verts.ndim != 3 or verts.shape[0] != num_frames or verts.shape[2] != 3:
        raise DatasetError(
            f"{mesh_path}: 'vertices' must have shape ({num_frames}, V, 3), got {verts.shape}"
        )
    if faces.size and (faces.min() < 0 or faces.max() >= verts.shape[1]):
        raise DatasetError(f"{mesh_path}: 'faces' index vertices out of range")
    if not (np.isfinite(verts).all() and np.abs(verts).max(initial=0) <= MAX_METRES):
        raise DatasetError(f"{mesh_path}: 'vertices' must be finite and within {MAX_METRES:g} m "
                           "of the origin")
    return faces, verts


def face_landmarks(meta: dict, where: str, num_vertices: int) -> dict[str, list[int]] | None:
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


def read_mesh_model(path: Path, num_vertices: int, dim: int
                    ) -> tuple[np.ndarray, np.ndarray, float, str] | None:
    """An expression_model.npz -> neutral (V, 3), basis (dim, V, 3) float32, finite, ridge,
    method; None where the dataset has none."""
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            neutral, basis = z["neutral"].astype(np.float32), z["basis"].astype(np.float32)
            ridge, method = float(z["ridge"]), str(z["method"])
    except KeyError as e:
        raise DatasetError(f"{path}: missing array {e}") from None
    except Exception as e:  # noqa: BLE001
        raise DatasetError(f"{path}: not a readable .npz ({type(e).__name__})") from None
    if neutral.shape != (num_vertices, 3) or basis.shape != (dim, num_vertices, 3):
        raise DatasetError(f"{path}: expected neutral ({num_vertices}, 3) and basis ({dim}, "
                           f"{num_vertices}, 3), got {neutral.shape} and {basis.shape}")
    if not (np.isfinite(neutral).all() and np.isfinite(basis).all()):
        raise DatasetError(f"{path}: holds non-finite values")
    return neutral, basis, ridge, method


def check_paths(root: Path, position: int, paths: tuple[str, ...], check_files: bool) -> None:
    """A frame's files (`paths`, relative to the dataset's folder `root`) lie inside the
    dataset and, with `check_files`, exist."""
    for rel in paths:
        # a dataset reads only its own files, not whatever path it names
        if Path(rel).is_absolute() or ".." in Path(rel).parts:
            raise DatasetError(f"{root / 'transforms.json'}: frames[{position}]: {rel!r} is "
                               "outside the dataset (paths are relative to its folder)")
        if check_files and not (root / rel).exists():
            raise DatasetError(f"{root / rel}: file is missing")
