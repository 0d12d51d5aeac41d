"""The baked avatar: splats of the scene as the run renders it at the reference expression,
and for the splats the spatial prior lets β reach, one linear offset per control.

A splat is a square facing the camera (a point sprite): a world position, a colour and a
world side length. Splat i at expression β:

    position_i(β) = position_i + Σ_k (β_k − reference_k) · d_position[k, j]
    colour_i(β)   = colour_i   + Σ_k (β_k − reference_k) · d_colour[k, j]

for the face splats j = face_index⁻¹(i); every other splat is the same for every β, so
nothing outside the face moves with the expression whatever the offsets hold.

Stored as one .npz of plain arrays (read with allow_pickle=False: loading runs no code).
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from flamenerf.errors import UserError
from flamenerf.io import atomic_write_bytes

FORMAT = "flamenerf-baked-splats"
VERSION = 1


@dataclass
class BakedAvatar:
    positions: np.ndarray  # (N, 3) float32 world
    colours: np.ndarray  # (N, 3) float32 in [0, 1]
    sizes: np.ndarray  # (N,) float32 world side length of each splat's square
    face_index: np.ndarray  # (F,) int64: the splats β reaches
    d_positions: np.ndarray  # (K, F, 3) float32 world per unit of control k
    d_colours: np.ndarray  # (K, F, 3) float32 per unit of control k
    names: list[str]  # (K,) the run's controls
    reference: np.ndarray  # (K,) float32: the expression the splats show as stored
    low: np.ndarray  # (K,) float32: each control's range (the render's and the sliders')
    high: np.ndarray  # (K,)
    meta: dict[str, Any] = field(default_factory=dict)  # camera of frame 0, intrinsics, run

    @property
    def n(self) -> int:
        return len(self.positions)

    def at(self, expression: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """expression (K,) -> positions (N, 3), colours (N, 3) of every splat (colours
        clipped to [0, 1])."""
        delta = np.asarray(expression, np.float32) - self.reference
        pos, col = self.positions.copy(), self.colours.copy()
        if len(self.face_index):
            pos[self.face_index] += np.einsum("k,kfc->fc", delta, self.d_positions)
            col[self.face_index] += np.einsum("k,kfc->fc", delta, self.d_colours)
        return pos, np.clip(col, 0.0, 1.0)

    def check(self, where: str = "baked avatar") -> None:
        """One-line UserError naming `where` when the arrays do not fit together."""
        n, k = len(self.positions), len(self.names)
        f = len(self.face_index)
        shapes = {"positions": (n, 3), "colours": (n, 3), "sizes": (n,),
                  "d_positions": (k, f, 3), "d_colours": (k, f, 3), "reference": (k,),
                  "low": (k,), "high": (k,)}
        for name, shape in shapes.items():
            if tuple(getattr(self, name).shape) != shape:
                raise UserError(f"{where}: damaged ({name} has shape "
                                f"{tuple(getattr(self, name).shape)}, expected {shape})")
        if f and (self.face_index.min() < 0 or self.face_index.max() >= n):
            raise UserError(f"{where}: damaged (face_index outside the {n} splats)")
        for name in ("positions", "colours", "sizes", "d_positions", "d_colours"):
            if not np.isfinite(getattr(self, name)).all():
                raise UserError(f"{where}: damaged ({name} holds non-finite values)")


_ARRAYS = ("positions", "colours", "sizes", "face_index", "d_positions", "d_colours",
           "reference", "low", "high")


def save_avatar(avatar: BakedAvatar, path: str | Path) -> Path:
    """Write the avatar as .npz, atomically, renamed only once it reads back whole with as
    many splats; -> path."""
    path = Path(path)
    avatar.check(str(path))
    header = {"format": FORMAT, "version": VERSION, "names": list(avatar.names),
              "meta": avatar.meta}
    arrays = {k: np.ascontiguousarray(getattr(avatar, k)) for k in _ARRAYS}

    def write(f) -> None:
        np.savez_compressed(f, header=np.frombuffer(json.dumps(header).encode(), np.uint8),
                            **arrays)

    def verify(tmp: Path) -> str | None:
        try:
            back = load_avatar(tmp)
        except UserError as e:
            return str(e)
        return None if back.n == avatar.n else f"{back.n} splats of {avatar.n}"

    atomic_write_bytes(path, write, verify)
    return path


def load_avatar(path: str | Path) -> BakedAvatar:
    """Read a baked avatar; a one-line UserError naming the file for anything else."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no baked avatar there (make one with `flamenerf bake RUN`)")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise UserError(f"{path}: not a baked avatar ({str(e).splitlines()[0][:80]})") from None
    missing = [k for k in ("header", *_ARRAYS) if k not in data]
    if missing:
        raise UserError(f"{path}: not a baked avatar (no {missing[0]!r} array)")
    try:
        header = json.loads(data["header"].tobytes().decode())
    except (UnicodeDecodeError, ValueError, RecursionError):
        raise UserError(f"{path}: damaged (its header is not JSON)") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise UserError(f"{path}: not a baked avatar (format {str(header)[:40]!r})")
    if header.get("version") != VERSION:
        raise UserError(f"{path}: baked by another flamenerf (format version "
                        f"{header.get('version')!r}, this one reads {VERSION}); bake again")
    names = header.get("names")
    if not isinstance(names, list) or not all(isinstance(s, str) for s in names):
        raise UserError(f"{path}: damaged ('names' is not a list of strings)")
    meta = header.get("meta") if isinstance(header.get("meta"), dict) else {}
    av = BakedAvatar(*(data[k].astype(np.int64 if k == "face_index" else np.float32)
                       for k in _ARRAYS[:6]), names,
                     *(data[k].astype(np.float32) for k in _ARRAYS[6:]), meta=meta)
    av.check(str(path))
    return av
