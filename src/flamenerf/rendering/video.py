"""Streaming mp4 writing (H.264 via imageio-ffmpeg) to a temporary file renamed into place,
so an interrupted render never leaves a truncated video under the final name."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from flamenerf.errors import UserError


def even_pad(img: np.ndarray) -> np.ndarray:
    """Pad an (H, W, 3) uint8 image with black to even sides (yuv420p needs them)."""
    h, w = img.shape[:2]
    ph, pw = h % 2, w % 2
    if ph or pw:
        img = np.pad(img, ((0, ph), (0, pw), (0, 0)))
    return img


class VideoWriter:
    """Frames in, one mp4 out. Use as a context manager: on success the temporary file is
    renamed to `path`; on an exception it is deleted.

        with VideoWriter(path, fps=30) as v:
            for frame in frames:
                v.write(frame)  # (H, W, 3) uint8 or float in [0, 1]
    """

    def __init__(self, path: str | os.PathLike, fps: float, quality: int = 8,
                 preset: str = "veryfast"):
        if fps <= 0:
            raise UserError(f"--fps must be positive, got {fps}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # the extension stays .mp4 so that ffmpeg picks the container from it
        self.tmp = self.path.with_name(f".{self.path.stem}.{os.getpid()}.tmp.mp4")
        self.fps, self.quality, self.preset = float(fps), quality, preset
        self._gen = None
        self._size: tuple[int, int] | None = None
        self.frames = 0

    def write(self, frame: np.ndarray) -> None:
        import imageio_ffmpeg

        from flamenerf.images import to_uint8

        img = even_pad(np.ascontiguousarray(to_uint8(np.asarray(frame))[..., :3]))
        h, w = img.shape[:2]
        if self._gen is None:
            logging.getLogger("imageio_ffmpeg").setLevel(logging.ERROR)
            self._size = (w, h)
            self._gen = imageio_ffmpeg.write_frames(
                str(self.tmp), (w, h), fps=self.fps, quality=self.quality, macro_block_size=2,
                ffmpeg_log_level="error", output_params=["-preset", self.preset])
            self._gen.send(None)
        elif (w, h) != self._size:
            raise ValueError(f"frame size {w}x{h} differs from the video's {self._size}")
        self._gen.send(np.ascontiguousarray(img))
        self.frames += 1

    def close(self) -> Path:
        if self._gen is None:
            raise UserError(f"{self.path}: no frames to write")
        self._gen.close()
        self._gen = None
        os.replace(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        if self._gen is not None:
            try:
                self._gen.close()
            except Exception:  # noqa: BLE001 - ffmpeg may already be gone
                pass
            self._gen = None
        self.tmp.unlink(missing_ok=True)

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def read_frames(path: str | os.PathLike) -> list[np.ndarray]:
    """Decode every frame of a video (for checks and tests)."""
    import imageio.v3 as iio

    return list(iio.imiter(path, plugin="FFMPEG"))
