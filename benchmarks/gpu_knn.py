"""The nearest-vertex kernel's choices timed on a GPU: vertex tiles (0: every vertex in
turn) and warps a block, on the queries of a trained run's frame (its most expressive β)
at one size, each against the first choice's answer (the same, index for index).

`gpu_kernels.KNN_TILE` / `KNN_WARPS` were chosen by registers a thread on sm_90
(gpu_build.py, benchmarks/gpu_kernels_build.py), not by time: this says which is fastest.

Usage: python benchmarks/gpu_knn.py --run RUN [--dataset SCENE] [--size 512]
        [--repeats 20] [--points 0] [--json OUT.json]
On a CPU (a check of the script): TRITON_INTERPRET=1 FLAMENERF_GPU_KERNELS=1
FLAMENERF_CPU_KERNELS=0 python benchmarks/gpu_knn.py ... --device cpu --points 128
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from pathlib import Path

import torch

from flamenerf import gpu_kernels
from flamenerf.model import inference
from flamenerf.model.gpu_emulation import gpu_path_on_cpu
from flamenerf.model.render_image import render_image
from flamenerf.training.run import load_run
from view_args import view_args, view_options

CHOICES = [(0, 4), (0, 8), (8, 4), (8, 8), (16, 4), (16, 8)]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    view_options(ap, size=512, device="cuda")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--points", type=int, default=0,
                    help="time only a query's first N points (0: all; the interpreter's "
                         "check takes ~2 s per 128 points and choice)")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()

    dev = torch.device(a.device)
    if not gpu_kernels.available(dev):
        print(f"gpu_knn: no Triton kernels on {dev}", file=sys.stderr)
        return 1
    run = load_run(a.run, dev)
    args = view_args(run, run.dataset(a.dataset), a.size, expressive=True)
    queries = []
    kernel = gpu_kernels.knn

    def kept(pts, meshes, which, k, **kw):
        n = a.points or len(pts)
        queries.append((pts[:n].clone(), meshes.clone(), which[:n].clone(), k))
        return kernel(pts, meshes, which, k, **kw)

    gpu_kernels.knn = kept
    try:
        with gpu_path_on_cpu() if dev.type == "cpu" else torch.inference_mode():
            render_image(*args, settings=dataclasses.replace(inference.FAST, threads=1))
    finally:
        gpu_kernels.knn = kernel
    if not queries:
        print("gpu_knn: the frame made no nearest-vertex queries", file=sys.stderr)
        return 1

    def sync() -> None:
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else "CPU (interpreter)"
    rows = []
    built = gpu_kernels._load()["knn"]
    for q, (pts, meshes, which, k) in enumerate(queries):
        if len(pts) == 0:
            continue
        first = None
        for tile, warps in CHOICES:
            got = kernel(pts, meshes, which, k, tile=tile, warps=warps)  # also the build
            if got is None:
                rows.append({"query": q, "tile": tile, "warps": warps, "error": "failed"})
                gpu_kernels._load()["knn"] = built  # one choice failing turned knn off
                continue
            same = first is None or (torch.equal(got[1], first[1])
                                     and bool((got[0] - first[0]).abs().max() < 1e-6))
            first = first or got
            times = []
            for _ in range(a.repeats):
                sync()
                t = time.perf_counter()
                kernel(pts, meshes, which, k, tile=tile, warps=warps)
                sync()
                times.append(time.perf_counter() - t)
            row = {"query": q, "points": len(pts), "vertices": meshes.shape[1], "k": k,
                   "tile": tile, "warps": warps, "ms_best": round(1e3 * min(times), 4),
                   "ms_median": round(1e3 * statistics.median(times), 4), "same": same}
            rows.append(row)
            print(f"query {q} ({len(pts)} points, {meshes.shape[1]} vertices, k {k}): "
                  f"tile {tile:2d}, {warps} warps: {row['ms_best']:.4f} ms best, "
                  f"{row['ms_median']:.4f} median{'' if same else ', DIFFERENT ANSWER'}",
                  flush=True)
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps({"device": name, "torch": torch.__version__,
                                      "size": a.size, "default": [gpu_kernels.KNN_TILE,
                                                                  gpu_kernels.KNN_WARPS],
                                      "rows": rows}, indent=1) + "\n")
    return 0 if all(r.get("same") for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
