"""The process and its hardware: allocator tuning (before any heavy work), the torch device,
CPU threads, native libraries' log lines."""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, TypeVar

from flamenerf.errors import UserError

if TYPE_CHECKING:
    import torch

T = TypeVar("T")
R = TypeVar("R")

TUNED_ALLOCATOR = {"MALLOC_MMAP_MAX_": "0", "MALLOC_TRIM_THRESHOLD_": "100000000000"}


def reexec_with_tuned_allocator(python_args: list[str]) -> None:
    """Re-run this process as `python *python_args` with glibc tuned, unless it already is.

    glibc returns large freed blocks to the OS and then page-faults them back on every
    training step; keeping them mapped made steps ~2x faster on CPU (PERF_NOTES.md). The
    variables are read at process start, hence the re-exec.
    """
    if not sys.platform.startswith("linux") or os.environ.get("FLAMENERF_NO_REEXEC"):
        return
    if all(os.environ.get(k) == v for k, v in TUNED_ALLOCATOR.items()):
        return
    env = dict(os.environ, **TUNED_ALLOCATOR, FLAMENERF_NO_REEXEC="1")
    try:
        os.execve(sys.executable, [sys.executable, *python_args], env)
    except OSError:  # an interpreter this user may not start again: run untuned, not fail
        return


def pick_device(device: str = "auto") -> torch.device:
    """`auto` -> CUDA when present, else CPU; `cpu`, `cuda` or `cuda:N` when this machine has
    it; anything else is a one-line UserError naming --device."""
    import torch

    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device)
    except RuntimeError:
        raise UserError(f"--device {device}: not a device (auto, cpu, cuda or cuda:N)") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise UserError(f"--device {device}: CUDA is not available on this machine "
                            "(use --device cpu or auto)")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise UserError(f"--device {device}: this machine has "
                            f"{torch.cuda.device_count()} CUDA device(s)")
    elif dev.type != "cpu":
        raise UserError(f"--device {device}: not supported (auto, cpu, cuda or cuda:N)")
    return dev


def gpu_inference(device: torch.device) -> bool:
    """Whether inference (torch's inference mode) on `device` takes the GPU's layers: the
    features written side by side in the autocast dtype, the expression fields contracted
    in the Triton kernel, the MLPs' lean layers (model/field.py, model/mlp.py). One place
    for the decision, so that a test can send a CPU run down that path under Triton's
    interpreter (tests/model/test_gpu_path.py): no GPU is needed to check its wiring."""
    return device.type == "cuda"


def set_threads(threads: int) -> None:
    """Use `threads` CPU threads for torch; 0 keeps torch's default; below 0 is a one-line
    UserError (--threads)."""
    if threads < 0:
        raise UserError(f"--threads {threads}: must be >= 0 (0: torch's default)")
    if threads > 0:
        import torch

        torch.set_num_threads(threads)


@contextlib.contextmanager
def torch_threads(threads: int) -> Iterator[None]:
    """Run the block with `threads` torch CPU threads, then restore the previous count."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def map_single_threaded(fn: Callable[[T], R], items: list[T], workers: int) -> list[R]:
    """[fn(x) for x in items] in `workers` Python threads that each run torch with one CPU
    thread, taking items in order as they come free; results in the items' order.

    For many small, independent pieces of torch work (chunks of rays at inference): one
    thread's Python overhead then overlaps another's arithmetic, where one Python thread
    driving all cores leaves them waiting between small ops (a 256 px `fast` frame on
    2 cores: median 1.11 -> 0.85 s, docs/bench/render_ab_threads.json). The process's
    thread count is restored afterwards; torch work that other threads start meanwhile gets
    one thread too."""
    import torch

    if workers <= 1 or len(items) <= 1:
        return [fn(x) for x in items]
    before = torch.get_num_threads()
    try:
        with ThreadPoolExecutor(workers, initializer=torch.set_num_threads,
                                initargs=(1,)) as pool:
            return list(pool.map(fn, items))
    finally:
        torch.set_num_threads(before)


@contextlib.contextmanager
def quiet_native_stderr() -> Iterator[None]:
    """Silence the log lines native libraries print to the process's stderr within the
    block (glog and TFLite while MediaPipe builds its graph; pycolmap's bundle adjustment,
    which sets its own log level). Set FLAMENERF_VERBOSE=1 to see them."""
    if os.environ.get("FLAMENERF_VERBOSE"):
        yield
        return
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no real fd 2 (e.g. some notebook kernels)
        yield
        return
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
