"""The GPU kernels' launch choices timed on a GPU, each against the first choice's answer:
the nearest-vertex kernel's vertex tiles (0: every vertex in turn) and warps a block, and
the field heads' points and warps a block, on the calls a trained run's frame makes (its
most expressive β) at one size.

`gpu_kernels.KNN_TILE` / `KNN_WARPS` and `HEADS_BLOCK` / `HEADS_WARPS` were first chosen
by registers a thread on sm_90 (gpu_build.py, benchmarks/gpu_kernels_build.py), then by
this script's times on an H200 (2026-11-28: the nearest vertices' 8 warps became 4). The nearest vertices must be the same, index for index; the
heads' σ and RGB within 1e-3 relative (another block shape may order a sum otherwise).

Usage: python benchmarks/gpu_choices.py --run RUN [--dataset SCENE] [--size 512]
        [--repeats 20] [--points 0] [--json OUT.json]
On a CPU (a check of the script): TRITON_INTERPRET=1 FLAMENERF_GPU_KERNELS=1
FLAMENERF_CPU_KERNELS=0 python benchmarks/gpu_choices.py ... --device cpu --points 128
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

KNN_CHOICES = [{"tile": t, "warps": w} for t in (0, 8, 16) for w in (4, 8)]
# 128 points with 2 warps or fewer spill on sm_80 and sm_90 (scratch builds, 2026-11-28)
HEADS_CHOICES = [{"block": b, "warps": w} for b in (64, 128) for w in (4, 8)]  # DOT_MIN


def record(run, dataset, size: int, points: int, dev: torch.device) -> dict[str, list]:
    """The knn and field-heads calls of one frame: {kernel: [(args, kwargs), ...]}, each
    cut to its first `points` points (0: all)."""
    calls = {"knn": [], "field_heads": []}
    knn, heads = gpu_kernels.knn, gpu_kernels.field_heads

    def kept_knn(pts, meshes, which, k, **kw):
        n = points or len(pts)
        calls["knn"].append(((pts[:n].clone(), meshes.clone(), which[:n].clone(), k), {}))
        return knn(pts, meshes, which, k, **kw)

    def kept_heads(feats, term, per, density_head, rgb_head, **kw):
        n = points or len(feats)
        calls["field_heads"].append(((feats[:n].clone(), term.clone(), per, density_head,
                                      rgb_head), {}))
        return heads(feats, term, per, density_head, rgb_head, **kw)

    gpu_kernels.knn, gpu_kernels.field_heads = kept_knn, kept_heads
    try:
        args = view_args(run, run.dataset(dataset), size, expressive=True)
        with gpu_path_on_cpu() if dev.type == "cpu" else torch.inference_mode():
            render_image(*args, settings=dataclasses.replace(inference.FAST, threads=1))
    finally:
        gpu_kernels.knn, gpu_kernels.field_heads = knn, heads
    return calls


def same_knn(got, first) -> bool:
    return torch.equal(got[1], first[1]) and bool((got[0] - first[0]).abs().max() < 1e-6)


def same_heads(got, first) -> bool:
    return all(torch.allclose(g, f, rtol=1e-3, atol=1e-4) for g, f in zip(got, first))


def time_choices(kernel: str, calls: list, choices: list[dict], same, repeats: int,
                 dev: torch.device) -> list[dict]:
    """Each choice on each recorded call: best and median ms over `repeats`, and whether
    its answer is the first choice's."""
    fn = getattr(gpu_kernels, kernel)

    def sync() -> None:
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)

    rows = []
    with torch.inference_mode():
        for q, (args, kw) in enumerate(calls):
            if len(args[0]) == 0:
                continue
            first = None
            for choice in choices:
                built = dict(gpu_kernels._load())
                got = fn(*args, **kw, **choice)  # also the build
                if got is None:
                    rows.append({"kernel": kernel, "call": q, **choice, "error": "failed"})
                    gpu_kernels._load().update(built)  # a failing choice turned it off
                    continue
                ok = first is None or same(got, first)
                first = first or got
                times = []
                for _ in range(repeats):
                    sync()
                    t = time.perf_counter()
                    fn(*args, **kw, **choice)
                    sync()
                    times.append(time.perf_counter() - t)
                row = {"kernel": kernel, "call": q, "points": len(args[0]), **choice,
                       "ms_best": round(1e3 * min(times), 4),
                       "ms_median": round(1e3 * statistics.median(times), 4), "same": ok}
                rows.append(row)
                shown = ", ".join(f"{k} {v}" for k, v in choice.items())
                print(f"{kernel} call {q} ({len(args[0])} points): {shown}: "
                      f"{row['ms_best']:.4f} ms best, {row['ms_median']:.4f} median"
                      f"{'' if ok else ', DIFFERENT ANSWER'}", flush=True)
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    view_options(ap, size=512, device="cuda")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--points", type=int, default=0,
                    help="time only a call's first N points (0: all; the interpreter's "
                         "check takes ~2 s per 128 points and choice)")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()

    dev = torch.device(a.device)
    if not gpu_kernels.available(dev):
        print(f"gpu_choices: no Triton kernels on {dev}", file=sys.stderr)
        return 1
    run = load_run(a.run, dev)
    calls = record(run, a.dataset, a.size, a.points, dev)
    rows = []
    for kernel, choices, same in (("knn", KNN_CHOICES, same_knn),
                                  ("field_heads", HEADS_CHOICES, same_heads)):
        if kernel not in gpu_kernels.working():
            print(f"gpu_choices: {kernel} is off (FLAMENERF_GPU_KERNELS)", file=sys.stderr)
            rows.append({"kernel": kernel, "skipped": "off"})
            continue
        if not calls[kernel]:
            print(f"gpu_choices: the frame made no {kernel} calls", file=sys.stderr)
            rows.append({"kernel": kernel, "error": "no calls"})
            continue
        rows += time_choices(kernel, calls[kernel], choices, same, a.repeats, dev)
    name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else "CPU (interpreter)"
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps({
            "device": name, "torch": torch.__version__, "size": a.size,
            "defaults": {"knn": {"tile": gpu_kernels.KNN_TILE, "warps": gpu_kernels.KNN_WARPS},
                         "field_heads": {"block": gpu_kernels.HEADS_BLOCK,
                                         "warps": gpu_kernels.HEADS_WARPS}},
            "rows": rows}, indent=1) + "\n")
    return 0 if all(r.get("same") for r in rows if "skipped" not in r) else 1


if __name__ == "__main__":
    sys.exit(main())
