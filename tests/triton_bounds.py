"""Every load and store of the Triton kernels, under Triton's interpreter, checked to fall
inside one of the launch's tensor arguments (tests/model/test_gpu_bounds.py). On a GPU an
access out of bounds ends the CUDA context ("illegal memory access"); under the
interpreter it reads or writes whatever lies there, silently. An access out of bounds is
recorded and raised before it happens (the kernel then fails: `gpu_kernels._launch` turns
it off)."""

from __future__ import annotations

import threading

import numpy as np
import torch
from triton.runtime import interpreter

from flamenerf import gpu_kernels

_launch = threading.local()
stats = {"launches": {}, "checked": 0, "out_of_bounds": {}}


def install() -> None:
    """Patch gpu_kernels' launches and the interpreter's masked loads and stores."""
    launch = gpu_kernels._launch

    def recorded(name, grid, *args, **meta):
        _launch.name = name
        _launch.ranges = [(t.data_ptr(), t.data_ptr() + (t.untyped_storage().nbytes()
                                                         - t.storage_offset() * t.element_size()))
                          for t in (*args, *meta.values()) if isinstance(t, torch.Tensor)]
        stats["launches"][name] = stats["launches"].get(name, 0) + 1
        return launch(name, grid, *args, **meta)

    def check(ptrs, mask, what: str) -> None:
        p = ptrs.data[np.broadcast_to(mask.data, ptrs.data.shape)].astype(np.uint64)
        stats["checked"] += len(p)
        inside = np.zeros(len(p), bool)
        for lo, hi in _launch.ranges:
            inside |= (p >= lo) & (p < hi)
        if not inside.all():
            key = f"{_launch.name} {what}"
            stats["out_of_bounds"][key] = stats["out_of_bounds"].get(key, 0) + int((~inside).sum())
            raise IndexError(f"{key}: {int((~inside).sum())} of {len(p)} addresses outside "
                             "the launch's tensors")

    load, store = (interpreter.InterpreterBuilder.create_masked_load,
                   interpreter.InterpreterBuilder.create_masked_store)

    def checked_load(self, ptrs, mask, *rest):
        check(ptrs, mask, "load")
        return load(self, ptrs, mask, *rest)

    def checked_store(self, ptrs, value, mask, *rest):
        check(ptrs, mask, "store")
        return store(self, ptrs, value, mask, *rest)

    gpu_kernels._launch = recorded
    interpreter.InterpreterBuilder.create_masked_load = checked_load
    interpreter.InterpreterBuilder.create_masked_store = checked_store
