"""Video decoding (imageio-ffmpeg) that honours rotation metadata, frame selection, and
H.264 writing to a temporary file renamed into place (an interrupted render or preprocess
never leaves a truncated video under the final name).

Phones store portrait videos as landscape frames plus a display-matrix rotation; ffmpeg
applies it while decoding (its default `autorotate`), so the frames we return, and the
`width`/`height` we report, are as the video is meant to be seen. `rotation` records the
angle for the report. Frame times are `index / fps`, or for a variable-rate clip each
frame's own presentation time (`VideoInfo.times`).

HDR clips (a phone's default HDR video: HLG or PQ, BT.2020 colours, 10 bits) are decoded
to SDR BT.709 (`SDR_FILTER`): taken as they are stored, they came out dim and pale.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flamenerf.errors import UserError, warn
from flamenerf.io import temporary_beside
from flamenerf.images import to_uint8


FPS_RANGE = (0.1, 1000.0)  # a frame every ten seconds to far above any player's rate:
# ffmpeg's muxer fails at extreme rates after printing its own lines


def check_fps(fps, where: str) -> float:
    """A frame rate within FPS_RANGE, else a one-line UserError naming `where`."""
    lo, hi = FPS_RANGE
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not lo <= fps <= hi:
        raise UserError(f"{where}: the frame rate must be a number from {lo:g} to {hi:g}, "
                        f"got {fps!r}")
    return float(fps)


@dataclass
class VideoInfo:
    path: Path
    width: int  # after rotation
    height: int
    fps: float
    num_frames: int
    duration: float
    rotation: int  # degrees the player rotates the stored frames (0, 90, 180, 270)
    codec: str
    hdr: str | None = None  # the HDR transfer (arib-std-b67: HLG, smpte2084: PQ), or None
    times: np.ndarray | None = None
    """(num_frames,) seconds from the first frame, each frame's own, for a variable-rate
    clip; None where the frames are evenly spaced (frame i at i / fps)."""

    def frame_time(self, index):
        """Seconds from the first frame of frame(s) `index` (int or (n,) array)."""
        if self.times is None:
            return np.asarray(index) / self.fps
        return self.times[np.asarray(index)]


HDR_TRANSFERS = ("arib-std-b67", "smpte2084")

REFERENCE_WHITE_NITS = 203
"""The luminance an HDR clip's SDR white is stored at (ITU-R BT.2408's reference white):
it decodes to the SDR white, brighter light is compressed into the top of the range."""

SDR_FILTER = (f"zscale=t=linear:npl={REFERENCE_WHITE_NITS},format=gbrpf32le,zscale=p=bt709,"
              "tonemap=tonemap=mobius:param=0.7:desat=0,zscale=t=bt709:m=bt709:r=tv,"
              "format=yuv420p")
"""ffmpeg's filters from an HDR clip to SDR BT.709: linear light, BT.709 primaries, Möbius
tone mapping (linear up to 0.7 of the range, the highlights above compressed rather than
clipped), BT.709's transfer. On test clips made from an SDR picture at the reference white
the frames come back within 6 grey levels of 255 on average, the white at 238 (decoded as
stored: 22 for HLG, 43 for PQ; Möbius's default transition of 0.3: 10, the white at 215;
Hable's curve: 46); not checked against a phone's own HDR clip."""


def _ffmpeg() -> str:
    import imageio_ffmpeg

    return imageio_ffmpeg.get_ffmpeg_exe()


def _duration(header: str) -> float | None:
    """The duration ffmpeg's header text states, in seconds (None if it states none)."""
    m = re.search(r"Duration: (\d+):(\d+):([\d.]+)", header)
    return None if m is None else int(m[1]) * 3600 + int(m[2]) * 60 + float(m[3])


def _header(path: Path) -> str:
    r = subprocess.run([_ffmpeg(), "-hide_banner", "-nostdin", "-i", str(path)],
                       capture_output=True, text=True, errors="replace")
    return r.stderr


def probe_video(path: str | os.PathLike) -> VideoInfo:
    """Read a video's header; UserError naming the file if it is missing or not a video."""
    import imageio_ffmpeg

    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: file does not exist")
    if not path.is_file():
        raise UserError(f"{path}: not a file")
    text = _header(path)
    vlines = [ln for ln in text.splitlines() if ln.lstrip().startswith("Stream") and
              " Video: " in ln]
    if not vlines:
        last = [ln.strip() for ln in text.splitlines() if ln.strip()]
        why = last[-1] if last else "ffmpeg cannot read it"
        if "Invalid data" in text or "moov atom" in text:
            why = "not a readable video file"
        elif "Audio:" in text or "Stream" in text:
            why = "has no video stream"
        raise UserError(f"{path}: not a readable video ({why})")
    line = vlines[0]
    m = re.search(r" (\d+)x(\d+)[ ,\[]", line)
    if not m:
        raise UserError(f"{path}: cannot read the frame size from the video header")
    w, h = int(m.group(1)), int(m.group(2))
    m = re.search(r"([0-9.]+) fps", line) or re.search(r"([0-9.]+) tbr", line)
    fps = float(m.group(1)) if m else 0.0
    rot = 0
    m = re.search(r"rotation of (-?[0-9.]+) degrees", text)
    if m:
        rot = int(round(float(m.group(1)))) % 360
    else:
        m = re.search(r"rotate\s*:\s*(-?\d+)", text)
        if m:
            rot = (-int(m.group(1))) % 360
    if rot in (90, 270):
        w, h = h, w
    codec = line.split("Video: ", 1)[-1].split(" ", 1)[0].strip(",")
    hdr = next((t for t in HDR_TRANSFERS if t in line), None)
    try:
        nframes, secs = imageio_ffmpeg.count_frames_and_secs(str(path))
    except Exception as e:  # noqa: BLE001 - ffmpeg failures come in many types
        raise UserError(f"{path}: not a readable video ({type(e).__name__})") from None
    if nframes <= 0:
        raise UserError(f"{path}: video has no frames")
    if fps <= 0:
        fps = nframes / secs if secs > 0 else 30.0
    packets = _packets(path)
    if "partial file" in packets.stderr:  # its index lists frames whose data is not there
        said = _duration(text)
        listed = f" of the {said:.1f} s its header gives" if said is not None else ""
        warn(f"{path}: the file is cut short (a copy or download that did not finish?): only "
             f"its first {int(nframes)} frames ({secs:.1f} s{listed}) can be read; using those")
    times = _frame_times(packets.stdout, int(nframes), fps)
    return VideoInfo(path, w, h, fps, int(nframes), float(secs), rot, codec, hdr, times)


def _packets(path: Path) -> subprocess.CompletedProcess:
    """ffmpeg's list of the first video stream's packets (framecrc, no decoding) on stdout,
    its complaints (a file cut short: "partial file") on stderr."""
    return subprocess.run([_ffmpeg(), "-hide_banner", "-nostdin", "-loglevel", "error", "-i",
                           str(path), "-map", "0:v:0", "-c", "copy", "-f", "framecrc", "-"],
                          capture_output=True, text=True, errors="replace")


def _frame_times(packets: str, nframes: int, fps: float) -> np.ndarray | None:
    """Each frame's presentation time, seconds from the first, from the stream's `packets`
    (`_packets`' list), where they are not evenly spaced at `fps` (more than half a frame
    off i / fps somewhere); None where they are, or where they cannot be read as one per
    frame."""
    m = re.search(r"^#tb 0: (\d+)/(\d+)", packets, re.M)
    try:
        pts = [int(ln.split(",")[2]) for ln in packets.splitlines()
               if ln and not ln.startswith("#")]
    except (IndexError, ValueError):
        return None
    if m is None or len(pts) != nframes or nframes < 2:
        return None
    t = np.sort(np.asarray(pts, np.float64)) * int(m.group(1)) / int(m.group(2))
    t -= t[0]
    return t if np.abs(t - np.arange(nframes) / fps).max() > 0.5 / fps else None


def select_frames(num_frames: int, native_fps: float, fps: float | None = None,
                  max_frames: int | None = None, times: np.ndarray | None = None
                  ) -> np.ndarray:
    """Indices of the frames to keep: subsample to `fps` (nearest source frame to each
    tick; by the frames' own `times` (num_frames,) seconds where given, a variable-rate
    clip's), then, when more than `max_frames` remain, that many spread evenly over the
    clip."""
    if num_frames <= 0:
        return np.zeros(0, np.int64)
    if fps is not None:
        check_fps(fps, "--fps")
    if max_frames is not None and max_frames <= 0:
        raise UserError(f"--max-frames must be positive, got {max_frames}")
    if fps is None or fps >= native_fps:
        idx = np.arange(num_frames)
    elif times is not None:
        ticks = np.arange(0.0, times[-1] + 0.5 / fps, 1.0 / fps)
        right = np.clip(np.searchsorted(times, ticks), 1, num_frames - 1)
        nearer_left = ticks - times[right - 1] <= times[right] - ticks
        idx = np.unique(np.where(nearer_left, right - 1, right)).astype(np.int64)
    else:
        step = native_fps / fps
        idx = np.unique(np.round(np.arange(0, num_frames - 0.5, step)).astype(np.int64))
        idx = idx[idx < num_frames]
    if max_frames is not None and len(idx) > max_frames:
        pick = np.unique(np.round(np.linspace(0, len(idx) - 1, max_frames)).astype(np.int64))
        idx = idx[pick]
    return idx


def iter_frames(info: VideoInfo, indices: np.ndarray | None = None
                ) -> Iterator[tuple[int, np.ndarray]]:
    """Yield (source frame index, (H, W, 3) uint8 RGB) for the frames in `indices` (all if
    None), in order, decoding the stream once. Frame i is the stream's i-th frame, as
    `probe_video` counts them: a variable-rate clip (a phone's in low light drops frames
    and keeps the nominal rate) is not resampled to a constant rate, which repeated frames
    in its gaps and shifted every later index."""
    import imageio_ffmpeg

    logging.getLogger("imageio_ffmpeg").setLevel(logging.ERROR)
    want = None if indices is None else set(int(i) for i in indices)
    last = -1 if want is None else max(want, default=-1)
    params = ["-fps_mode", "passthrough"]
    if info.hdr is not None:
        params += ["-vf", SDR_FILTER]
    gen = imageio_ffmpeg.read_frames(str(info.path), pix_fmt="rgb24", output_params=params)
    try:
        meta = next(gen)
        w, h = meta["size"]
        if (w, h) != (info.width, info.height):
            # ffmpeg applied a different rotation than the header suggested; trust the data
            info.width, info.height = int(w), int(h)
        nbytes = w * h * 3
        for i, buf in enumerate(gen):
            if want is not None and i > last:
                break
            if want is not None and i not in want:
                continue
            if len(buf) != nbytes:
                break
            yield i, np.frombuffer(buf, np.uint8).reshape(h, w, 3)
    except (RuntimeError, OSError, StopIteration) as e:
        why = _ffmpeg_reason(e)
        if info.hdr is not None and "filter" in why.lower():
            why += (" - this ffmpeg cannot tone-map the HDR clip to SDR (it needs the zscale "
                    "and tonemap filters, which imageio-ffmpeg's own ffmpeg has)")
        raise UserError(f"{info.path}: decoding failed ({why})") from None
    finally:
        gen.close()


def _ffmpeg_reason(e: BaseException) -> str:
    """One line for a failed ffmpeg run: imageio-ffmpeg's errors carry ffmpeg's whole log
    (banner, configuration, streams); its last lines say what went wrong."""
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    said = [ln for ln in lines if any(w in ln for w in ("No such", "Error", "error",
                                                            "Invalid", "not found"))]
    return (said[0] if said else lines[0] if lines else type(e).__name__)[:200]


def even_pad(img: np.ndarray) -> np.ndarray:
    """Pad an (H, W, 3) uint8 image with black to even sides (yuv420p needs them)."""
    h, w = img.shape[:2]
    ph, pw = h % 2, w % 2
    if ph or pw:
        img = np.pad(img, ((0, ph), (0, pw), (0, 0)))
    return img


@dataclass(frozen=True)
class Soundtrack:
    """The sound of the video `source` from `start` seconds on: what a video of the clip's
    own frames, played at the clip's pace, carries."""

    source: Path
    start: float


def has_sound(path: str | os.PathLike) -> bool:
    """Whether a video file has an audio stream."""
    return any(ln.lstrip().startswith("Stream") and " Audio: " in ln
               for ln in _header(Path(path)).splitlines())


SILENT_DB = -60.0
"""A sound track whose loudest sample is below this (dB of full scale) carries nothing to
hear: a phone's muted recording reads about -90."""


def loudest(sound: Soundtrack, duration: float) -> float | None:
    """The loudest sample of `sound`'s first `duration` seconds, in dB of full scale (-inf
    for digital silence), by ffmpeg's volumedetect; None where ffmpeg cannot tell."""
    r = subprocess.run(
        [_ffmpeg(), "-hide_banner", "-nostdin", "-ss", f"{sound.start:.6f}", "-t",
         f"{duration:.6f}", "-i", str(sound.source), "-map", "0:a:0", "-af", "volumedetect",
         "-f", "null", "-"], capture_output=True, text=True, errors="replace")
    found = re.search(r"max_volume:\s*(-?inf|-?[\d.]+) dB", r.stderr)
    return None if r.returncode or found is None else float(found.group(1))


def video_packets(path: Path) -> int | None:
    """How many frames of video `path`'s first video stream holds, counted from its packets
    (no decoding: one packet per H.264 frame); None where ffmpeg finds no such stream or
    fails part way (a file cut short)."""
    r = _packets(path)
    if r.returncode != 0 or r.stderr.strip():
        return None
    return sum(1 for ln in r.stdout.splitlines() if ln and not ln.startswith("#"))


def check_video(path: Path, frames: int, sound: bool = False) -> str | None:
    """Why the mp4 at `path` is not a whole video of `frames` frames (with a sound track
    where `sound`), or None: what a writer reads back before the file gets its name. ffmpeg
    stopped by a full disk or a file-size limit leaves a file without its index, which this
    catches (its exit status does not reach us through imageio-ffmpeg)."""
    n = video_packets(path)
    if n is None:
        return "ffmpeg cannot read back its video stream"
    if n != frames:
        return f"it holds {n} of the {frames} frames written"
    if sound and not has_sound(path):
        return "its sound track is missing"
    return None


def sound_duration(path: str | os.PathLike) -> float | None:
    """Seconds of sound in a file (a video's or a sound file's, by its header); None where
    it has no audio stream or states no duration."""
    text = _header(Path(path))
    if not any(ln.lstrip().startswith("Stream") and " Audio: " in ln
               for ln in text.splitlines()):
        return None
    return _duration(text)


def add_sound(video: Path, sound: Soundtrack, duration: float, out: Path) -> str | None:
    """Write `video` with `sound` cut, or padded with silence, to `duration` seconds to `out`
    (the picture copied, not encoded again); None on success, else ffmpeg's reason."""
    r = subprocess.run(
        [_ffmpeg(), "-hide_banner", "-nostdin", "-y", "-loglevel", "error", "-i", str(video),
         "-ss", f"{sound.start:.6f}", "-i", str(sound.source), "-map", "0:v:0", "-map",
         "1:a:0", "-c:v", "copy", "-c:a", "aac", "-af", "apad", "-t", f"{duration:.6f}",
         "-f", "mp4", str(out)],
        capture_output=True, text=True, errors="replace")
    if r.returncode == 0 and out.is_file():
        return None
    out.unlink(missing_ok=True)
    lines = [ln.strip() for ln in r.stderr.splitlines() if ln.strip()]
    return lines[-1] if lines else f"ffmpeg exit status {r.returncode}"


def write_wav(path: str | os.PathLike, sound: Soundtrack, duration: float) -> Path:
    """`sound`'s first `duration` seconds (padded with silence where it is shorter) as a
    16-bit PCM wav at `path`, written to a temporary, read back and renamed. -> path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_beside(path)
    try:
        r = subprocess.run(
            [_ffmpeg(), "-hide_banner", "-nostdin", "-y", "-loglevel", "error", "-ss",
             f"{sound.start:.6f}", "-i", str(sound.source), "-map", "0:a:0", "-vn", "-af",
             "apad", "-t", f"{duration:.6f}", "-c:a", "pcm_s16le", "-f", "wav", str(tmp)],
            capture_output=True, text=True, errors="replace")
        got = sound_duration(tmp) if r.returncode == 0 else None
        if got is None or abs(got - duration) > 0.05:
            lines = [ln.strip() for ln in r.stderr.splitlines() if ln.strip()]
            why = lines[-1] if lines else f"{got} s read back of {duration:.3f} s"
            raise UserError(f"{path}: not written: the sound ({sound.source}) could not be "
                            f"written ({why})")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


class VideoWriter:
    """Frames in, one mp4 out. Use as a context manager: on success the temporary file is
    renamed to `path`; on an exception it is deleted.

        with VideoWriter(path, fps=30) as v:
            for frame in frames:
                v.write(frame)  # (H, W, 3) uint8 or float in [0, 1]
    """

    def __init__(self, path: str | os.PathLike, fps: float, quality: int = 8,
                 preset: str = "veryfast", sound: Soundtrack | None = None):
        """`sound`: added to the video when it closes, cut to its length (a warning and a
        silent video where ffmpeg cannot)."""
        check_fps(fps, str(path))
        self.sound = sound
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # named as every temporary (flamenerf.io.temp_prefix), so that one a kill -9 left is
        # recognised; the container is named to ffmpeg, not read from the extension
        self.tmp = temporary_beside(self.path)
        self.fps, self.quality, self.preset = float(fps), quality, preset
        self._gen = None
        self._size: tuple[int, int] | None = None
        self.frames = 0

    def write(self, frame: np.ndarray) -> None:
        import imageio_ffmpeg

        img = even_pad(np.ascontiguousarray(to_uint8(np.asarray(frame))[..., :3]))
        h, w = img.shape[:2]
        if self._gen is None:
            logging.getLogger("imageio_ffmpeg").setLevel(logging.ERROR)
            self._size = (w, h)
            self._gen = imageio_ffmpeg.write_frames(
                str(self.tmp), (w, h), fps=self.fps, quality=self.quality, macro_block_size=2,
                ffmpeg_log_level="error", output_params=["-preset", self.preset, "-f", "mp4"])
            with self._ffmpeg():
                self._gen.send(None)
        elif (w, h) != self._size:
            raise ValueError(f"frame size {w}x{h} differs from the video's {self._size}")
        with self._ffmpeg():
            self._gen.send(np.ascontiguousarray(img))
        self.frames += 1

    def close(self) -> Path:
        """Finish the video, read it back (`check_video`) and give it its name. -> the path."""
        if self._gen is None:
            raise UserError(f"{self.path}: no frames to write")
        try:
            with self._ffmpeg():
                self._gen.close()
                self._gen = None
            self._check(self.tmp, sound=False)
            if self.sound is not None:
                self._add_sound()
            os.replace(self.tmp, self.path)
        except BaseException:  # nothing half written stays, under any name
            self.tmp.unlink(missing_ok=True)
            raise
        return self.path

    def _check(self, path: Path, sound: bool) -> None:
        why = check_video(path, self.frames, sound)
        if why is not None:
            raise UserError(f"{self.path}: not written: the video read back is not whole "
                            f"({why}; is the disk full?)")

    def _add_sound(self) -> None:
        mixed = temporary_beside(self.path)
        try:
            why = add_sound(self.tmp, self.sound, self.frames / self.fps, mixed)
            if why is None:
                self._check(mixed, sound=True)
                os.replace(mixed, self.tmp)
            else:  # the picture, read back whole already, stays
                warn(f"{self.path}: written without the sound of {self.sound.source} "
                     f"(ffmpeg: {why})")
        finally:
            mixed.unlink(missing_ok=True)

    @contextlib.contextmanager
    def _ffmpeg(self):
        """ffmpeg's failures (a broken pipe, its own error) as one line naming the video
        being written, not the temporary file."""
        try:
            yield
        except (OSError, RuntimeError) as e:
            if isinstance(e, OSError) and e.filename and Path(e.filename) != self.tmp:
                raise  # the machine's (a full disk elsewhere): cli names that file
            why = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise UserError(f"{self.path}: ffmpeg could not write the video ({why})") from None

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


def write_video(path: str | os.PathLike, frames: list[np.ndarray] | Iterator[np.ndarray],
                fps: float, quality: int = 8) -> None:
    """Write RGB uint8 frames as H.264 mp4."""
    with VideoWriter(path, fps, quality) as vw:
        for fr in frames:
            vw.write(fr)


def read_frames(path: str | os.PathLike) -> list[np.ndarray]:
    """Decode every frame of a video (for checks and tests)."""
    import imageio.v3 as iio

    return list(iio.imiter(path, plugin="FFMPEG"))
