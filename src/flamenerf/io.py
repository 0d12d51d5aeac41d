"""Files: atomic writes (bytes, text, JSON, PNG) and JSON reading.

Every output is written to a temporary file in its directory and renamed over the target,
so a crash or Ctrl-C never leaves a half-written file where a reader expects a whole one.
Every temporary file or folder flamenerf makes is a hidden sibling named
`.NAME.flamenerf-PID-XXXXXXXX` (NAME: the final name; PID: the writing process; see
`temp_prefix`), so one whose process is gone, left by a kill -9 or a crash, can be recognised
and removed (flamenerf.outdir.clean_stale_temps).
"""

from __future__ import annotations

import errno
import json
import math
import os
import re
import tempfile
from pathlib import Path
from typing import Any, BinaryIO, Callable

import numpy as np

from flamenerf.errors import UserError
from flamenerf.images import to_uint8


def temp_prefix(name: str) -> str:
    """Prefix for mkstemp/mkdtemp of a temporary that becomes `name` (module docstring)."""
    return f".{name}.flamenerf-{os.getpid()}-"


# what mkstemp/mkdtemp make with `temp_prefix`: the final name, the PID, 8 random characters
TEMP_NAME = re.compile(r"^\.(?P<name>.+)\.flamenerf-(?P<pid>\d+)-[a-z0-9_]{8}$")


class NotWritten(OSError):
    """An output whose file, read back before it got its final name, is not what was
    written (a full disk or a file-size limit that cut it short): nothing was renamed."""


def temporary_beside(path: str | os.PathLike) -> Path:
    """A new empty temporary file beside `path`, named for it (`temp_prefix`), readable as
    an ordinary output once renamed (0644); an OSError names `path`, not the temporary.
    For writers that hand a file name to another program (ffmpeg)."""
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=temp_prefix(path.name), dir=path.parent)
    except OSError as e:
        raise OSError(e.errno, e.strerror, str(path)) from None
    os.close(fd)
    os.chmod(tmp, 0o644)  # mkstemp makes 0600
    return Path(tmp)


def atomic_write_bytes(path: str | os.PathLike, write: Callable[[BinaryIO], object],
                       verify: Callable[[Path], str | None] | None = None) -> None:
    """Call `write(f)` on a temporary file in `path`'s directory, check it (its size is what
    was written; `verify(temporary)`: None, or why the file is not right), then rename it
    over `path`. Any failure leaves `path` as it was and raises an OSError naming `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_beside(path)
    try:
        try:
            with open(tmp, "wb") as f:
                write(f)
                f.flush()
                os.fsync(f.fileno())
                size = f.tell()
        except OSError as e:  # a full disk says "No space left" of no file: name ours
            raise OSError(e.errno, e.strerror, str(path)) from None
        why = (f"{os.path.getsize(tmp)} bytes on disk of {size} written"
               if os.path.getsize(tmp) != size else verify(tmp) if verify else None)
        if why is not None:
            raise NotWritten(errno.EIO, f"not written: the file read back is not whole "
                             f"({why}; is the disk full?)", str(path))
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write `text` atomically; the file is read back and compared before it is renamed."""
    data = text.encode()

    def same(tmp: Path) -> str | None:
        return None if tmp.read_bytes() == data else "its bytes differ from those written"

    atomic_write_bytes(path, lambda f: f.write(data), same)


def jsonable(x: Any) -> Any:
    """Plain JSON values of nested dicts/lists/tuples of numbers, NumPy values and paths:
    NumPy arrays and scalars become Python lists and numbers, paths strings, dict keys
    strings, and NaN/inf None (strict JSON has no NaN)."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, np.generic):
        x = x.item()
    if isinstance(x, Path):
        return str(x)
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def write_json(path: str | os.PathLike, obj: Any, indent: int | None = 1) -> None:
    """Atomically write `jsonable(obj)` as JSON."""
    atomic_write_text(path, json.dumps(jsonable(obj), indent=indent))


def read_json(path: str | os.PathLike, what: str | None = None) -> Any:
    """Parse a JSON file; a missing, unreadable or malformed file is a one-line UserError
    naming it (`what`: the kind of file, for the message)."""
    path = Path(path)
    if path.is_dir():
        raise UserError(f"{path}: is a folder; give the {what or 'file'} itself")
    if not path.is_file():
        raise UserError(f"{path}: {what} does not exist" if what else f"{path}: file is missing")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise UserError(f"{path}: not valid JSON (line {e.lineno}: {e.msg})") from None
    except UnicodeDecodeError:
        raise UserError(f"{path}: not valid JSON (not UTF-8 text)") from None
    except RecursionError:
        raise UserError(f"{path}: not valid JSON here (nested too deeply to read)") from None


def save_png(path: str | os.PathLike, img: np.ndarray) -> None:
    """Atomically write an (H, W[, 3]) float-in-[0, 1] or uint8 image as PNG, decoded again
    before it gets its name."""
    import imageio.v3 as iio

    pixels = to_uint8(np.asarray(img))
    data = iio.imwrite("<bytes>", pixels, extension=".png")

    def decodes(tmp: Path) -> str | None:
        try:
            back = iio.imread(tmp, extension=".png")
        except Exception as e:  # noqa: BLE001 - a cut PNG fails in the decoder's own ways
            return f"it does not decode: {type(e).__name__}"
        return None if np.array_equal(back, pixels) else "its pixels differ from those written"

    atomic_write_bytes(path, lambda f: f.write(data), decodes)
