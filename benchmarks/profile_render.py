"""Where one frame's time goes: torch.profiler's table of a trained run's frame 0, rendered
by the inference path (or `--settings REFERENCE`) at one size, after a warm-up frame.
On a GPU the table is sorted by device time: the way docs/bench/gpu_h100_20261126_prof512.txt
found what to remove from a 512 px frame.

Usage: python benchmarks/profile_render.py --run RUN [--dataset SCENE] [--device cuda]
        [--size 512] [--frames 3] [--rows 40] [--out FILE]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

from flamenerf.model import inference
from flamenerf.model.render_image import render_image
from flamenerf.training.run import load_run
from view_args import view_args, view_options


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    view_options(ap, size=512)
    ap.add_argument("--settings", choices=["FAST", "VIEWER", "REFERENCE"], default="FAST")
    ap.add_argument("--frames", type=int, default=3, help="frames profiled (after a warm-up)")
    ap.add_argument("--rows", type=int, default=40, help="rows of the table")
    ap.add_argument("--out", type=Path, default=None, help="also write the table here")
    a = ap.parse_args()

    dev = torch.device(a.device)
    run = load_run(a.run, dev)
    args = view_args(run, run.dataset(a.dataset), a.size)
    # one thread on a CPU: the profiler sees only the thread that starts it
    settings = dataclasses.replace(getattr(inference, a.settings), threads=1)

    def frame() -> None:
        render_image(*args, settings=settings)
        if dev.type == "cuda":
            torch.cuda.synchronize()

    frame()  # warm-up: bakes, kernel builds, allocator
    cuda = dev.type == "cuda"
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=activities) as prof:
        for _ in range(a.frames):
            frame()
    key = "self_cuda_time_total" if cuda else "self_cpu_time_total"
    name = torch.cuda.get_device_name(dev) if cuda else "CPU"
    from flamenerf import gpu_kernels

    kernels = (", Triton kernels on: " + (", ".join(gpu_kernels.working()) or "none")
               if cuda else "")
    table = (f"# {a.settings} frame, {a.size} px, {a.frames} frames, {name}, "
             f"torch {torch.__version__}{kernels}\n"
             + prof.key_averages().table(sort_by=key, row_limit=a.rows, max_name_column_width=55))
    print(table)
    if a.out:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
