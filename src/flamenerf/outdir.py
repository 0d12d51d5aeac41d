"""Where flamenerf writes: output folders checked before the slow work, temporaries of our
own naming (cleaned when the same command starts again), and the rule for `--overwrite`
(replace only a folder flamenerf wrote).

Temporaries are named by flamenerf.io.temp_prefix (`.NAME.flamenerf-PID-XXXXXXXX`) and
renamed into place when complete; one whose process is gone was left by a kill -9 or a
crash and can go.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import tempfile
from pathlib import Path

from flamenerf.errors import UserError, warn
from flamenerf.io import TEMP_NAME, temp_prefix

# What `flamenerf synth` / `preprocess` write at the top of a dataset, and `train` (plus
# eval/render/bench, which write inside it) in a run folder.
DATASET_LAYOUT = {"transforms.json", "images", "masks", "depth", "moving", "face_mesh.npz",
                  "qa", "expression_model.npz"}
LOCK_NAME = ".flamenerf.lock"  # the lock of the process writing a folder (flamenerf.lock)
RUN_LAYOUT = {"config.json", "checkpoints", "tb", "images", "eval", "renders",
              "bench_timing.json", LOCK_NAME}


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def clean_stale_temps(folder: Path, name_pattern: str = r".+",
                      legacy: re.Pattern | None = None) -> list[Path]:
    """Remove temporaries in `folder` whose final name matches `name_pattern` and whose
    writer is gone (see the module docstring); `legacy` also matches the names of an older
    flamenerf, which did not record the PID (only for folders no other program writes in).
    Returns what was removed."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    want = re.compile(name_pattern)
    gone = []
    for p in folder.iterdir():
        m = TEMP_NAME.match(p.name)
        stale = (m is not None and want.fullmatch(m["name"]) is not None
                 and not _alive(int(m["pid"])))
        if not stale and (legacy is None or not legacy.fullmatch(p.name)):
            continue
        try:
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink()
            gone.append(p)
        except OSError:
            pass  # best effort: a leftover we cannot remove is no reason to stop
    return gone


def writable_dir(path: Path, what: str) -> Path:
    """Create folder `path` if needed and prove that files can be made in it, so that an
    unusable output fails in one line before the slow work, not after."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UserError(f"{path}: is a file, not a folder (give a folder for the {what})")
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=temp_prefix("probe"), dir=path)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise UserError(f"{path}: cannot write the {what} here ({e.strerror})") from None
    return path


def missing_folders(path: Path) -> list[Path]:
    """The folders that making `path` would create, deepest first (none if it exists)."""
    path, out = Path(path).absolute(), []
    while not path.exists() and path != path.parent:
        out.append(path)
        path = path.parent
    return out


def remove_if_empty(folders: list[Path]) -> None:
    """Remove those of `folders` (deepest first) that hold nothing: what a command made for
    an output it then failed to write."""
    for f in folders:
        try:
            f.rmdir()
        except OSError:
            return  # not empty, or not ours to remove: the folders above it stay too


@contextlib.contextmanager
def folders_kept_only_on_success(path: Path, remove: bool = True):
    """Within the block, a command makes `path` (a folder) and writes into it; where the
    block raises, the folders in and up to `path` that did not exist before it and are
    still empty go again (`remove`: False on the processes of a distributed run that do
    not write), so a failed command leaves no empty folder behind."""
    made = missing_folders(path)
    before = {Path(d) for d, _, _ in os.walk(path)}
    try:
        yield
    except BaseException:
        if remove:
            for d, _, _ in list(os.walk(path, topdown=False)):
                if Path(d) not in before and Path(d) != Path(path):
                    with contextlib.suppress(OSError):  # not empty: it stays
                        Path(d).rmdir()
            remove_if_empty(made)
        raise


def _is_dataset(path: Path) -> bool:
    try:
        meta = json.loads((path / "transforms.json").read_text())
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(meta, dict) and "format_version" in meta and "frames" in meta


def _is_run(path: Path) -> bool:
    try:
        meta = json.loads((path / "config.json").read_text())
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(meta, dict) and "flamenerf_version" in meta


# `render --frames-dir`'s folder (rendering/frame_folder.py): numbered PNGs, their index
FRAMES_LAYOUT = re.compile(r"\d{6}\.png|frames\.json|sound\.wav")


def _is_frames(path: Path) -> bool:
    return (path / "frames.json").is_file()


_KINDS = {"dataset": (DATASET_LAYOUT, _is_dataset), "run": (RUN_LAYOUT, _is_run),
          "frames folder": (FRAMES_LAYOUT, _is_frames)}


def _in_layout(name: str, layout: set[str] | re.Pattern) -> bool:
    return (layout.fullmatch(name) is not None if isinstance(layout, re.Pattern)
            else name in layout)


def check_replaceable(path: Path, kind: str) -> None:
    """Raise unless `path` is absent, an empty folder, or a `kind` ("dataset", "run" or
    "frames folder") that flamenerf wrote: its signature file parses and nothing else sits beside the
    known layout. `--overwrite` must never delete a user's own files."""
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        return
    if path.is_symlink() or not path.is_dir():
        raise UserError(f"{path}: is not a folder; --overwrite only replaces a {kind} "
                        "folder made by flamenerf")
    layout, signature = _KINDS[kind]
    entries = sorted(p.name for p in path.iterdir())
    if not entries:
        return
    if not signature(path):
        raise UserError(f"{path}: not a {kind} made by flamenerf; refusing to replace it "
                        "(remove it yourself or choose another output)")
    foreign = [e for e in entries if not _in_layout(e, layout)]
    if foreign:
        shown = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
        raise UserError(f"{path}: holds files flamenerf did not write ({shown}); refusing "
                        "to replace it (move them away or choose another output)")


def replace_dir(tmp: Path, out: Path, kind: str) -> None:
    """Move the finished folder `tmp` to `out`, replacing a previous `kind` there: the old
    one is renamed aside first, so some complete version exists at every moment."""
    old = None
    if out.exists():
        check_replaceable(out, kind)  # again: files may have appeared while we worked
        old = Path(tempfile.mkdtemp(prefix=temp_prefix(out.name), dir=out.parent))
        os.replace(out, old / out.name)
    os.replace(tmp, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
        if old.exists():
            warn(f"{old}: could not remove the replaced {kind}")
