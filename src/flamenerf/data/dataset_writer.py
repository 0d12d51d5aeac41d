"""Writing a dataset (`synth`, `preprocess`): frames, masks, depth and the face mesh into a
temporary sibling folder renamed into place whole, and the β -> mesh model stored with a
dataset afterwards. Read back by data/dataset.load_dataset."""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from flamenerf.data.dataset import FORMAT_VERSION, MESH_MODEL_FILE, Intrinsics, StoredMeshModel
from flamenerf.data.dataset_checks import DatasetError
from flamenerf.io import atomic_write_bytes, temp_prefix
from flamenerf.outdir import check_replaceable, clean_stale_temps, replace_dir, writable_dir

MAX_SIZE = 4096  # pixels a side that `synth` and `preprocess` make frames of


def write_mesh_model(root: str | os.PathLike, model: StoredMeshModel) -> Path:
    """Store a β -> mesh model in a dataset (atomically; read back by `load_dataset`)."""
    path = Path(root) / MESH_MODEL_FILE
    atomic_write_bytes(path, lambda f: np.savez(
        f, neutral=model.neutral.astype(np.float32), basis=model.basis.astype(np.float32),
        ridge=np.float64(model.ridge), method=np.str_(model.method)))
    return path


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
