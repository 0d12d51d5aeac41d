"""`flamenerf export --web`: a baked avatar as a self-contained folder a browser opens from
disk or any static server: index.html, player.js (WebGL2, viewer/web/) and avatar.js, the
bake's arrays as base64 in one script (a page opened from disk may not fetch files beside
it, but it may load scripts), with the track to play if one was given. No network, no
Python."""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from flamenerf.errors import UserError
from flamenerf.io import atomic_write_bytes
from flamenerf.splats.avatar import BakedAvatar
from flamenerf.splats.rasterise import BULGE

PAGE_FILES = ("index.html", "player.js")


@dataclass
class Exported:
    folder: Path
    bytes: int
    splats: int
    track_frames: int

    def describe(self) -> str:
        track = f", a track of {self.track_frames} frames" if self.track_frames else ""
        return (f"exported {self.splats} splats{track} ({self.bytes / 1e6:.1f} MB) to "
                f"{self.folder}: open {self.folder / 'index.html'} in a browser")


def _b64(a: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(a).tobytes()).decode("ascii")


def avatar_script(avatar: BakedAvatar, track: tuple[np.ndarray, float] | None = None) -> str:
    """avatar.js: `window.FLAMENERF_AVATAR = {...}`, arrays as little-endian base64
    (float32 positions and sizes, bytes of colour, int32 face rows, float16 offsets: what
    the bake stored, quantised there so that the reference rasteriser draws the same)."""
    data = {
        "n": avatar.n, "f": int(len(avatar.face_index)), "names": list(avatar.names),
        "reference": avatar.reference.astype(float).round(6).tolist(),
        "low": avatar.low.astype(float).round(6).tolist(),
        "high": avatar.high.astype(float).round(6).tolist(),
        "meta": avatar.meta, "bulge": BULGE,
        "positions": _b64(avatar.positions.astype("<f4")),
        "colours": _b64(np.round(avatar.colours * 255).clip(0, 255).astype(np.uint8)),
        "sizes": _b64(avatar.sizes.astype("<f4")),
        "faceIndex": _b64(avatar.face_index.astype("<i4")),
        "dPositions": _b64(avatar.d_positions.astype("<f2")),
        "dColours": _b64(avatar.d_colours.astype("<f2")),
        "track": None if track is None else {
            "fps": float(track[1]), "values": np.asarray(track[0], float).round(4).tolist()},
    }
    return "window.FLAMENERF_AVATAR = " + json.dumps(data) + ";\n"


def export_web(avatar: BakedAvatar, out: Path, track: tuple[np.ndarray, float] | None = None,
               overwrite: bool = False) -> Exported:
    """Write the page into `out` (a new or empty folder, or one this exported before with
    `overwrite`); each file is renamed into place only once it reads back whole."""
    check_web_folder(out, overwrite)
    files = {name: resources.files("flamenerf.viewer").joinpath("web", name).read_bytes()
             for name in PAGE_FILES}
    files["avatar.js"] = avatar_script(avatar, track).encode()
    total = 0
    for name, content in files.items():
        def verify(tmp: Path, content=content) -> str | None:
            return None if tmp.read_bytes() == content else "its bytes differ"

        atomic_write_bytes(Path(out) / name, lambda f, content=content: f.write(content), verify)
        total += len(content)
    return Exported(Path(out), total, avatar.n, 0 if track is None else len(track[0]))


def check_web_folder(out: Path, overwrite: bool = False) -> None:
    """A one-line UserError unless `out` can take the page: new, empty, or an earlier
    export with `overwrite` (checked before a bake, not after it)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: is a file; give a folder for the page")
    if out.is_dir() and any(out.iterdir()):
        ours = {p.name for p in out.iterdir()} <= {*PAGE_FILES, "avatar.js"}
        if not ours:
            raise UserError(f"{out}: holds other files; give a new or empty folder")
        if not overwrite:
            raise UserError(f"{out}: an export is there already (--overwrite to replace it)")
