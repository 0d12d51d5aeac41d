"""One writer per folder: a lock file that the process writing a run (or an evaluation)
holds for as long as it writes.

The lock is an advisory `flock` on `FOLDER/.flamenerf.lock`, which the kernel releases when
its process ends however it ends (a kill -9 too), so a lock left by a dead process is simply
taken over, with a note naming it. The file records who holds it (PID, host, command, start)
for the message a second writer gets. On network file systems without `flock` the lock
holds between processes of one machine only.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import socket
import sys
import time
from pathlib import Path

from flamenerf.errors import UserError, warn
from flamenerf.outdir import LOCK_NAME, missing_folders, remove_if_empty, writable_dir


def _holder(fd: int) -> dict:
    """What the lock file open at `fd` says of its holder ({} if nothing readable)."""
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        info = json.loads(os.read(fd, 4096).decode() or "{}")
    except (OSError, ValueError, RecursionError):
        return {}
    return info if isinstance(info, dict) else {}


def _described(info: dict) -> str:
    pid, host, cmd = info.get("pid"), info.get("host"), info.get("command")
    since = info.get("started")
    where = f" on {host}" if host and host != socket.gethostname() else ""
    when = (f", since {time.strftime('%H:%M:%S', time.localtime(since))}"
            if isinstance(since, (int, float)) else "")
    what = f" (`{cmd}`)" if isinstance(cmd, str) and cmd else ""
    return f"process {pid}{where}{when}{what}" if pid else "another process"


def _acquire(path: Path) -> tuple[int, dict]:
    """Open and lock `path`; -> (fd, what the file said of an earlier holder). A held lock
    is a UserError naming its holder."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            info = _holder(fd)
            os.close(fd)
            raise UserError(f"{path.parent}: being written by {_described(info)}; wait for "
                            "it to finish, or choose another output folder") from None
        except OSError:
            os.close(fd)
            raise
        # a holder that finished unlinks the file after we opened it: the lock we hold is
        # then on a file nobody else will open, so take the one at the path again
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            return fd, _holder(fd)
        os.close(fd)


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike, what: str, hold: bool = True):
    """Hold `folder`'s lock (making the folder, checked writable for the `what`) for the
    block; a second writer gets a one-line UserError. `hold` False: no lock (processes of a distributed run other than
    the one that writes). Where the block raises, the folders it made and left empty go
    again, as flamenerf.outdir.folders_kept_only_on_success does."""
    if not hold:
        yield
        return
    folder = Path(folder)
    made = missing_folders(folder)
    try:
        writable_dir(folder, what)
        path = folder / LOCK_NAME
        fd, earlier = _acquire(path)
    except OSError as e:
        remove_if_empty(made)
        raise UserError(f"{folder}: cannot write here ({e.strerror or e})") from None
    except BaseException:
        remove_if_empty(made)
        raise
    ok = False
    try:
        if earlier.get("pid"):
            warn(f"{folder}: took over the lock of {_described(earlier)}, which has ended "
                 "without releasing it")
        mine = {"pid": os.getpid(), "host": socket.gethostname(),
                "command": " ".join(["flamenerf", *sys.argv[1:]])[:200], "started": time.time()}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(mine).encode(), 0)
        yield
        ok = True
    finally:
        # unlinked while still held: a writer waiting on this file then retakes the path
        with contextlib.suppress(OSError):
            path.unlink()
        os.close(fd)
        if not ok:
            remove_if_empty(made)
