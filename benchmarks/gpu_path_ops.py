"""What one frame down the GPU's inference path asks of the host, counted on a CPU: the
ATen operations dispatched (on a GPU each is a launch or at least a Python-and-dispatcher
call; a 256 px frame there is bound by them) and those that wait for the device (nonzero,
boolean indexing, a tensor read as a Python number), per pass of the renderer (the
proposal, the main samples, the second pass over unfinished rays). The render goes down
the GPU path on the CPU (model/gpu_emulation.py, float32; its passes are the GPU's: one
chunk, the proposal checked once per ray); the Triton kernels run under the interpreter
only when FLAMENERF_GPU_KERNELS asks for them (then TRITON_INTERPRET=1: slow), so the
default here is the path with none (`FLAMENERF_GPU_KERNELS=0`). A count, not a time: it
says how much host work a change to the inference path adds or removes without a GPU.

Usage: FLAMENERF_GPU_KERNELS=0 python benchmarks/gpu_path_ops.py --run RUN [--size 128]
        [--json OUT]
"""

from __future__ import annotations

import argparse
import collections
import sys
from pathlib import Path

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from flamenerf.model import gpu_emulation, inference
from flamenerf.model.render_image import render_image
from flamenerf.training.run import load_run
from view_args import view_args, view_options

# views and metadata: no kernel of their own on a GPU
VIEWS = {"view", "_unsafe_view", "reshape", "slice", "select", "unsqueeze", "squeeze",
         "expand", "t", "transpose", "permute", "detach", "alias", "as_strided", "unbind",
         "split", "split_with_sizes", "chunk", "narrow", "diagonal", "lift_fresh", "unfold"}
WAITS = {"nonzero", "_local_scalar_dense", "is_nonzero", "masked_select", "item",
         "unique", "_unique2", "unique_dim", "equal"}


class Counter(TorchDispatchMode):
    """Counts each dispatched op under the renderer's current pass."""

    def __init__(self):
        super().__init__()
        self.phase = "setup"
        self.ops = collections.Counter()
        self.views = collections.Counter()
        self.waits = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.overloadpacket.__name__
        if name in VIEWS:
            self.views[self.phase] += 1
        else:
            self.ops[self.phase] += 1
        bool_index = name in ("index", "index_put", "index_put_") and any(
            i is not None and i.dtype == torch.bool for i in (args[1] or ()))
        if name in WAITS or bool_index:
            self.waits[self.phase] += 1
        return func(*args, **(kwargs or {}))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    view_options(ap, size=128, device=None)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()

    run = load_run(a.run, torch.device("cpu"))
    args = view_args(run, run.dataset(a.dataset), a.size)
    counter = Counter()
    passes = iter(["proposal", "main", "second pass"])
    march = inference.march

    def counted_march(*args_, **kw):
        counter.phase = next(passes, "more")
        try:
            return march(*args_, **kw)
        finally:
            counter.phase = "between passes"

    inference.march = counted_march
    try:
        with gpu_emulation.gpu_path_on_cpu(half=False):
            render_image(*args, settings=inference.FAST)  # the bakes, made once per ω
            passes = iter(["proposal", "main", "second pass"])
            counter.phase = "setup"
            with counter:
                render_image(*args, settings=inference.FAST)
    finally:
        inference.march = march
    from flamenerf import gpu_kernels

    phases = sorted(set(counter.ops) | set(counter.views))
    out = {"run": str(a.run), "size": a.size,
           "kernels": gpu_kernels.working() if gpu_kernels.available(torch.device("cpu"))
           else [],
           "ops": sum(counter.ops.values()), "views": sum(counter.views.values()),
           "waits": sum(counter.waits.values()),
           "by_pass": {p: {"ops": counter.ops[p], "views": counter.views[p],
                           "waits": counter.waits[p]} for p in phases}}
    if a.json:
        from flamenerf.io import write_json

        a.json.parent.mkdir(parents=True, exist_ok=True)
        write_json(a.json, out)
    print(f"{a.size} px frame down the GPU path: {out['ops']} ops (+{out['views']} views), "
          f"{out['waits']} waits for the device" + (f" (written to {a.json})" if a.json else ""))
    for p in phases:
        print(f"  {p:15s} {counter.ops[p]:5d} ops  {counter.views[p]:5d} views  "
              f"{counter.waits[p]:3d} waits")
    return 0


if __name__ == "__main__":
    sys.exit(main())
