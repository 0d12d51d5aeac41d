"""Files: atomic writes (bytes, text, JSON, PNG) and JSON reading.

Every output is written to a temporary file in its directory and renamed over the target,
so a crash or Ctrl-C never leaves a half-written file where a reader expects a whole one.
Every temporary file or folder flamenerf makes is a hidden sibling named
`.NAME.flamenerf-PID-XXXXXXXX` (NAME: the final name; PID: the writing process; see
`temp_prefix`), so one whose process is gone, left by a kill -9 or a crash, can be recognised
and removed (flamenerf.outdir.clean_stale_temps).
"""

from __future__ import annotations

import json
import math
import os
import re
import tempfile
from pathlib import Path
from typing import Any, BinaryIO, Callable

import numpy as np

from flamenerf.errors import UserError


def temp_prefix(name: str) -> str:
    """Prefix for mkstemp/mkdtemp of a temporary that becomes `name` (module docstring)."""
    return f".{name}.flamenerf-{os.getpid()}-"


# what mkstemp/mkdtemp make with `temp_prefix`: the final name, the PID, 8 random characters
TEMP_NAME = re.compile(r"^\.(?P<name>.+)\.flamenerf-(?P<pid>\d+)-[a-z0-9_]{8}$")


def atomic_write_bytes(path: str | os.PathLike, write: Callable[[BinaryIO], object]) -> None:
    """Call `write(f)` on a temporary file in `path`'s directory, then rename it over `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd, tmp = tempfile.mkstemp(prefix=temp_prefix(path.name), dir=path.parent)
    except OSError as e:  # name the file asked for, not our temporary's name
        raise OSError(e.errno, e.strerror, str(path)) from None
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)  # mkstemp makes 0600; outputs are ordinary files
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write_bytes(path, lambda f: f.write(text.encode()))


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


def save_png(path: str | os.PathLike, img: np.ndarray) -> None:
    """Atomically write an (H, W[, 3]) float-in-[0, 1] or uint8 image as PNG."""
    import imageio.v3 as iio

    from flamenerf.images import to_uint8

    data = iio.imwrite("<bytes>", to_uint8(np.asarray(img)), extension=".png")
    atomic_write_bytes(path, lambda f: f.write(data))
