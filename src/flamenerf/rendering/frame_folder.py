"""`render --frames-dir DIR`: a render as numbered PNG frames, for editing further without
the video codec's loss (H.264 4:2:0 halves the colour resolution and quantises the rest).

DIR holds `000000.png`, `000001.png`, ... (one per frame of the video, at its rate: a frame
held over a gap is written again), `frames.json` (rate, count, size, and the sound's file),
and `sound.wav` where the video has sound. It is written into a hidden temporary folder
beside DIR and renamed into place once every frame was read back, so DIR is whole or
absent; a DIR that flamenerf wrote before is replaced only with --overwrite.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

from flamenerf.data.video import Soundtrack, write_wav
from flamenerf.errors import UserError
from flamenerf.io import save_png, temp_prefix, write_json
from flamenerf.outdir import check_replaceable, replace_dir

INDEX = "frames.json"
SOUND = "sound.wav"


def check_frames_dir(path: Path, overwrite: bool) -> None:
    """Refuse (one line) a DIR that cannot take the frames: a file, a folder of other
    things (flamenerf.outdir.check_replaceable), or frames of an earlier render without
    --overwrite."""
    entries = sorted(p.name for p in path.iterdir()) if path.is_dir() else []
    if entries and not (path / INDEX).is_file():  # not ours at all: say what is there
        raise UserError(f"{path}: holds other files ({', '.join(entries[:3])}); "
                        "--frames-dir writes a new or empty folder, or one it wrote before")
    check_replaceable(path, "frames folder")  # a file; our frames with files added
    if entries and not overwrite:
        raise UserError(f"{path}: holds the frames of an earlier render (pass --overwrite to "
                        "replace them, or name another --frames-dir)")


class FrameFolder:
    """Frames in, a folder of PNGs out (module docstring). Use as a context manager: on
    success the folder gets its name; on an exception it is removed."""

    def __init__(self, path: Path, fps: float, sound: Soundtrack | None = None):
        self.path, self.fps, self.sound = Path(path), float(fps), sound
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = Path(tempfile.mkdtemp(prefix=temp_prefix(self.path.name),
                                         dir=self.path.parent))
        self.frames = 0
        self.size: tuple[int, int] | None = None

    def write(self, frame: np.ndarray) -> None:
        h, w = np.asarray(frame).shape[:2]
        if self.size is None:
            self.size = (w, h)
        save_png(self.tmp / f"{self.frames:06d}.png", frame)
        self.frames += 1

    def close(self) -> Path:
        if self.frames == 0:
            raise UserError(f"{self.path}: no frames to write")
        seconds = self.frames / self.fps
        if self.sound is not None:
            write_wav(self.tmp / SOUND, self.sound, seconds)
        write_json(self.tmp / INDEX, {
            "fps": self.fps, "frames": self.frames, "width": self.size[0],
            "height": self.size[1], "seconds": seconds,
            "sound": SOUND if self.sound is not None else None,
            "names": "%06d.png"})
        replace_dir(self.tmp, self.path, "frames folder")
        return self.path

    def abort(self) -> None:
        shutil.rmtree(self.tmp, ignore_errors=True)

    def __enter__(self) -> "FrameFolder":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            try:
                self.close()
            except BaseException:
                self.abort()
                raise
        else:
            self.abort()
