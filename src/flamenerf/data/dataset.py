"""The one dataset format, written by `synth` and `preprocess`, read by everything else.
What `load_dataset` refuses is data/dataset_checks.py's, the writer data/dataset_writer.py,
and how a clip's frames play in time data/playback.py.

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
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from flamenerf.data import dataset_checks as checks
from flamenerf.data.dataset_checks import DatasetError
from flamenerf.data.playback import frame_rate
from flamenerf.errors import warn

FORMAT_VERSION = 1
CAPTURE = "capture"
"""The split every dataset has without storing it: its capture frames (train and val) in
the order of their codes, which is the clip's (`Dataset.split`)."""


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


def load_dataset(root: str | os.PathLike, check_files: bool = True) -> Dataset:
    """Read and validate a dataset; any problem becomes one DatasetError naming the file
    (data/dataset_checks.py)."""
    root = Path(root)
    meta = checks.read_transforms(root)
    where = str(root / "transforms.json")
    checks.check_header(meta, where, FORMAT_VERSION)
    intr = Intrinsics(*checks.intrinsics_fields(meta, where))
    near, far = checks.near_far(meta, where)
    kind, names = checks.expression_model(meta, where)
    raw_frames = checks.raw_frames(meta, where)
    frames = [Frame(position=i, **checks.frame_fields(fr, f"{where} frames[{i}]", len(names),
                                                      len(raw_frames)))
              for i, fr in enumerate(raw_frames)]
    checks.check_head_poses([f.head_pose is not None for f in frames], where)
    splits = checks.splits(meta, where, [f.frame_index for f in frames])
    faces, verts = checks.read_face_mesh(root / "face_mesh.npz", len(frames))
    landmarks = checks.face_landmarks(meta, where, verts.shape[1])
    mesh_model = checks.read_mesh_model(root / MESH_MODEL_FILE, verts.shape[1], len(names))
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
        mesh_model=None if mesh_model is None else StoredMeshModel(*mesh_model),
    )
    for fr in frames:
        checks.check_paths(root, fr.position, fr.paths, check_files)
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

