"""The compiled CPU kernels: built on first use with the system's C compiler and cached;
without a compiler the callers run their PyTorch (or SciPy) paths instead (with a warning).

- kernels/hashgrid.c: the hash grid's encoding, forward and backward (model/encodings.py,
  the bakes of model/baked.py);
- kernels/knn.c: the k nearest mesh vertices of many points (meshes.nearest_vertices).

Small C files called through ctypes, rather than a PyTorch C++ extension: both compile in
1.4 s on the 2-core development machine (-march=native; 0.4 s portable), once per CPU and
source, and need nothing beyond `cc` (an extension would compile torch's headers and need
ninja). `FLAMENERF_CPU_KERNELS=0` turns them off (to compare, or to debug).
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
import warnings
from pathlib import Path

_SOURCES = [Path(__file__).with_name("kernels") / name for name in ("hashgrid.c", "knn.c")]
_FLAGS = ["-O3", "-fPIC", "-shared", "-fopenmp"]
# compiled for the CPU at hand (AVX-512: the hash grid's forward pass 1.3-1.9x faster on the
# development machine's Zen 4, the nearest-vertex walk vectorised at all); the cache key
# names that CPU, so a cache shared between machines never hands one another's build
_NATIVE = ["-march=native"]
_lib: ctypes.CDLL | None = None
_tried = False


def cache_dir() -> Path:
    root = os.environ.get("FLAMENERF_CACHE")
    if root is None:
        xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
        root = str(Path(xdg) / "flamenerf")
    return Path(root) / "kernels"


def cpu_identity() -> str:
    """What a -march=native build depends on: the CPU's model and feature flags."""
    import platform

    try:
        with open("/proc/cpuinfo") as f:
            info = [ln for ln in f if ln.startswith(("model name", "flags", "Features"))]
        return "".join(sorted(set(info))) or platform.processor()
    except OSError:
        return platform.machine() + platform.processor()


def _build(cc: str, out: Path, flags: list[str]) -> None:
    """Compile into a temporary file beside `out`, then rename: concurrent processes (test
    workers, a benchmark next to a run) never load a half-written library."""
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
    os.close(fd)
    try:
        subprocess.run([cc, *flags, *map(str, _SOURCES), "-o", tmp, "-lm"], check=True,
                       capture_output=True, text=True)
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def kernel_library() -> ctypes.CDLL | None:
    """The compiled kernels, or None (disabled, no compiler, or the build failed)."""
    global _lib, _tried
    if _tried:
        return _lib
    _tried = True
    if os.environ.get("FLAMENERF_CPU_KERNELS", "1") == "0":
        return None
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        warnings.warn("flamenerf: no C compiler (cc) found; the hash grid runs as plain "
                      "PyTorch, several times slower on a CPU, and the nearest mesh "
                      "vertices through SciPy's k-d tree", stacklevel=2)
        return None
    lib, errors = None, []
    for flags in (_FLAGS + _NATIVE, _FLAGS):  # without -march=native where cc lacks it
        key = hashlib.sha256(b"".join(f.read_bytes() for f in _SOURCES)
                             + " ".join([cc, *flags]).encode()
                             + (cpu_identity().encode() if _NATIVE[0] in flags else b""))
        so = cache_dir() / f"kernels-{key.hexdigest()[:16]}.so"
        try:
            if not so.exists():
                _build(cc, so, flags)
            lib = ctypes.CDLL(str(so))
            break
        except (OSError, subprocess.CalledProcessError) as e:
            errors.append((getattr(e, "stderr", "") or str(e)).strip())
    if lib is None:
        warnings.warn(f"flamenerf: building the CPU kernels failed ({errors[-1][:200]}); "
                      "using the slower PyTorch hash grid and SciPy's k-d tree", stacklevel=2)
        return None
    p, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int32
    lib.hashgrid_forward.argtypes = [p, i64, i32, i32, p, p, p, i64, p, i64, i32]
    lib.hashgrid_backward.argtypes = [p, i64, i32, i32, p, p, p, i64, p, p, p, p, i32]
    lib.hashgrid_contract.argtypes = [p, i64, i32, i32, p, p, p, i64, p, i32, p, i64, i32]
    lib.hashgrid_forward.restype = lib.hashgrid_backward.restype = None
    lib.hashgrid_contract.restype = None
    lib.knn_forward.argtypes = [p, i64, p, p, i64, i64, i32, ctypes.c_double, p, p, i32]
    lib.knn_forward.restype = lib.knn_vectorised.restype = ctypes.c_int
    lib.knn_vectorised.argtypes = []
    _lib = lib
    return lib
