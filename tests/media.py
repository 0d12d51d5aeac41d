"""Videos and datasets made by the tests, shared by tests/data, tests/tracking and
tests/synthetic (registered as a pytest plugin in tests/conftest.py): short videos made from
scikit-image's astronaut photo (a real face), face-less and rotated videos, and a small
built-in scene."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest


@pytest.fixture(scope="session")
def dataset_dir(tmp_path_factory) -> Path:
    """The built-in scene at 48x48: 12 capture frames (val: frame 5), 3 reanimate, one
    leakage step."""
    from flamenerf.synthetic.scene import make_scene

    out = tmp_path_factory.mktemp("synth") / "scene"
    make_scene(out, seed=1, size=48, frames=12, reanimate=3, leakage_steps=1, workers=1)
    return out


def _warp(img: np.ndarray, zoom: float, dx: float, dy: float, out: int) -> np.ndarray:
    """Crop-and-zoom of img around its face (a hand-held camera, roughly)."""
    from PIL import Image

    h, w = img.shape[:2]
    cx, cy = 0.4 * w + dx, 0.32 * h + dy  # the astronaut's face is up and left of centre
    half = 0.3 * w / zoom
    box = (cx - half, cy - half, cx + half, cy + half)
    return np.asarray(Image.fromarray(img).resize((out, out), Image.Resampling.BICUBIC,
                                                  box=box))


def astronaut_frames(n: int = 12, size: int = 256, seed: int = 0) -> list[np.ndarray]:
    from skimage import data

    img = data.astronaut()
    rng = np.random.default_rng(seed)
    frames = []
    for k in range(n):
        t = k / max(1, n - 1)
        frames.append(_warp(img, 1.0 + 0.15 * t, 20 * np.sin(3 * t) + rng.normal(0, 1),
                            10 * t + rng.normal(0, 1), size))
    return frames


def write_mp4(path: Path, frames: list[np.ndarray], fps: float = 10.0) -> Path:
    from flamenerf.data.video import write_video

    write_video(path, frames, fps=fps, quality=9)
    return path


@pytest.fixture(scope="session")
def astronaut_video(tmp_path_factory) -> Path:
    return write_mp4(tmp_path_factory.mktemp("vid") / "astronaut.mp4", astronaut_frames())


def two_faces_frames(n: int = 8) -> list[np.ndarray]:
    """The astronaut twice, side by side in 480x300 frames: the left face shrinks from 220
    to 187 px while the right one grows as much, so the most prominent face changes sides
    two thirds of the way (whom a tracker of one face follows then jumps). Both are found
    in every frame (MediaPipe misses a face much smaller than the other)."""
    from skimage import data

    img = data.astronaut()
    frames = []
    for k in range(n):
        t = k / max(1, n - 1)
        out = np.full((300, 480, 3), 120, np.uint8)
        for zoom, right in ((1.0 - 0.15 * t, False), (0.85 + 0.15 * t, True)):
            face = _warp(img, 1.0, 0, 0, int(220 * zoom))
            s = face.shape[0]
            x = 470 - s if right else 10
            out[150 - s // 2:150 - s // 2 + s, x:x + s] = face
        frames.append(out)
    return frames


@pytest.fixture(scope="session")
def two_faces_video(tmp_path_factory) -> Path:
    return write_mp4(tmp_path_factory.mktemp("vid") / "two_faces.mp4", two_faces_frames())


def cut_frames(n: int = 24, cut: int = 12) -> list[np.ndarray]:
    """The astronaut filmed in two shots: a slow push-in, then from frame `cut` another
    framing (closer, shifted), as an edited clip's jump cut."""
    from skimage import data

    img = data.astronaut()
    frames = []
    for k in range(n):
        t = k / max(1, n - 1)
        frames.append(_warp(img, 1.0 + 0.05 * t, 10 * t, 0, 256) if k < cut
                      else _warp(img, 1.35 + 0.05 * t, -40 + 10 * t, 25, 256))
    return frames


@pytest.fixture(scope="session")
def cut_video(tmp_path_factory) -> Path:
    return write_mp4(tmp_path_factory.mktemp("vid") / "cut.mp4", cut_frames())


@pytest.fixture(scope="session")
def gappy_video(tmp_path_factory) -> Path:
    """12 frames, frames 3 and 7 without a face (grey)."""
    frames = astronaut_frames()
    for k in (3, 7):
        frames[k] = np.full_like(frames[k], 128)
    return write_mp4(tmp_path_factory.mktemp("vid") / "gappy.mp4", frames)


@pytest.fixture(scope="session")
def noface_video(tmp_path_factory) -> Path:
    from skimage import data

    coffee = data.coffee()[:256, :256]
    frames = [np.roll(coffee, 4 * k, axis=1) for k in range(6)]
    return write_mp4(tmp_path_factory.mktemp("vid") / "noface.mp4", frames)


@pytest.fixture(scope="session")
def mostly_noface_video(tmp_path_factory) -> Path:
    """10 frames, only 2 with a face."""
    frames = astronaut_frames(10)
    for k in range(2, 10):
        frames[k] = np.full_like(frames[k], 90)
    return write_mp4(tmp_path_factory.mktemp("vid") / "mostly_noface.mp4", frames)


@pytest.fixture(scope="session")
def rotated_video(tmp_path_factory) -> Path:
    """A 320x160 stream with a 90° display rotation (how phones store portrait video)."""
    import imageio_ffmpeg

    d = tmp_path_factory.mktemp("vid")
    frames = [np.zeros((160, 320, 3), np.uint8) for _ in range(5)]
    for k, f in enumerate(frames):
        f[:, :40] = 255  # a white band on the stored frame's left edge
        f[:8, :, 1] = 20 * k
    plain = write_mp4(d / "plain.mp4", frames)
    out = d / "rotated.mp4"
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error",
                    "-display_rotation", "90", "-i", str(plain), "-c", "copy", str(out)],
                   check=True)
    return out


def variable_rate_clip(path: Path, n: int = 20, gap_after: int = 10) -> Path:
    """n flat frames of grey 10·k at 30 fps with a 0.5 s gap after frame `gap_after` (as a
    phone drops frames in low light), stored at their variable rate."""
    import imageio_ffmpeg

    frames = np.concatenate([np.full((1, 32, 32, 3), 10 * k, np.uint8) for k in range(n)])
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-f",
                    "rawvideo", "-pix_fmt", "rgb24", "-s", "32x32", "-r", "30", "-i", "-",
                    "-vf", f"setpts='(N+if(gte(N\\,{gap_after})\\,15\\,0))/30/TB'",
                    "-fps_mode", "passthrough", "-c:v", "libx264", "-qp", "0",
                    "-pix_fmt", "yuv444p", str(path)], input=frames.tobytes(), check=True)
    return path


def hdr_clip(path: Path, transfer: str, frames: np.ndarray) -> Path:
    """SDR frames (N, H, W, 3) uint8 stored as a phone's HDR video: HEVC, 10 bits, BT.2020
    colours, `transfer` HLG (arib-std-b67) or PQ (smpte2084), SDR white at BT.2408's
    reference white (203 nits), losslessly."""
    import imageio_ffmpeg

    n, h, w, _ = frames.shape
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-f",
                    "rawvideo", "-pix_fmt", "rgb24", "-s", f"{w}x{h}", "-r", "10", "-i", "-",
                    "-vf", "zscale=tin=iec61966-2-1:min=gbr:pin=bt709:rin=full:"
                    f"t={transfer}:m=bt2020nc:p=bt2020:r=tv:npl=203,format=yuv420p10le",
                    "-c:v", "libx265", "-x265-params",
                    f"log-level=error:lossless=1:colorprim=bt2020:transfer={transfer}:"
                    "colormatrix=bt2020nc", "-color_primaries", "bt2020", "-color_trc",
                    transfer, "-colorspace", "bt2020nc", str(path)],
                   input=np.ascontiguousarray(frames).tobytes(), check=True)
    return path


def clip_with_sound(path, seconds: float = 3.0, volume: float = 1.0):
    """A 32 px clip with a 440 Hz tone (`volume` 0: a silent sound track, as a muted
    phone records), made by ffmpeg's own generators."""
    from flamenerf.data.video import _ffmpeg

    subprocess.run([_ffmpeg(), "-nostdin", "-y", "-loglevel", "error", "-f", "lavfi", "-i",
                    f"color=c=red:s=32x32:d={seconds}:r=30", "-f", "lavfi", "-i",
                    f"sine=frequency=440:duration={seconds}", "-af", f"volume={volume}",
                    "-c:v", "libx264", "-c:a", "aac", "-shortest", str(path)], check=True)
    return path
