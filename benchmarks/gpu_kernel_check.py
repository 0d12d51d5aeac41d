"""Which Triton kernel fails or differs on this GPU: one frame of an untrained preset
rendered down the inference path with the kernels off, all on, each alone and all but
each, every render in a fresh process (an illegal memory access ends a CUDA context), and
each image compared with the kernels-off render. Prints a table and writes JSON.

    python benchmarks/gpu_kernel_check.py --device cuda --sizes 128 512 --json check.json

On a CPU the kernels run under Triton's interpreter (TRITON_INTERPRET=1, set here), down
the GPU's path (model/gpu_emulation.py): slow, tiny sizes only (--sizes 16).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
KERNELS = ("hashgrid", "knn", "field_heads")


def child(args) -> None:
    import numpy as np
    import torch

    sys.path.insert(0, str(HERE))
    from bench_render import FAST, camera, untrained

    from flamenerf.model.render_image import render_image

    from flamenerf import gpu_kernels

    if args.heads:  # BLOCK,WARPS[,DOT_MIN]
        h = [int(v) for v in args.heads[0].split(",")]
        gpu_kernels.HEADS_BLOCK, gpu_kernels.HEADS_WARPS = h[:2]
        if len(h) > 2:
            gpu_kernels.DOT_MIN = h[2]
    dev = torch.device(args.device)
    m = untrained(args.preset, dev)
    w, a = m.codes(torch.tensor([0], device=dev))
    intr, c2w = camera(args.size)
    mask = np.zeros((args.size, args.size), bool)
    mask[args.size // 4: 3 * args.size // 4, args.size // 3: 2 * args.size // 3] = True
    expr = torch.full((m.expr_dim,), 0.3)
    if dev.type == "cpu":
        from flamenerf.model.gpu_emulation import gpu_path_on_cpu
        ctx = gpu_path_on_cpu(half=True)
    else:
        import contextlib
        ctx = contextlib.nullcontext()
    with ctx:
        out = render_image(m, intr, c2w, w[0].detach(), a[0].detach(), expr, mask,
                           settings=FAST)
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
    np.save(args.save, np.asarray(out["rgb"].float().cpu() if hasattr(out["rgb"], "cpu")
                                  else out["rgb"], dtype=np.float32))


def configs(heads: list[str]) -> list[tuple[str, str, str]]:
    """(label, FLAMENERF_GPU_KERNELS, field_heads' BLOCK,WARPS or '') triples; the first
    is the reference."""
    out = [("off", "0", ""), ("all", "1", "")]
    out += [(f"{k} alone", k, "") for k in KERNELS]
    out += [(f"all but {k}", ",".join(x for x in KERNELS if x != k), "") for k in KERNELS]
    out += [(f"field_heads {h.replace(',', 'x')}", "field_heads", h) for h in heads]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--sizes", type=int, nargs="+", default=[128])
    ap.add_argument("--timeout", type=float, default=180.0, help="seconds per render")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--heads", nargs="*", default=[],
                    help="field_heads launches BLOCK,WARPS[,DOT_MIN] to try alone besides the "
                    "default (16,4,16: as before 2026-11-28)")
    ap.add_argument("--only", help="the configurations to run, by label, comma-separated")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--size", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--save", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args)
        return 0
    import tempfile

    import numpy as np

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes:
            ref = None
            for label, chosen, heads in configs(args.heads):
                if args.only and label not in args.only.split(","):
                    continue
                save = f"{tmp}/{size}_{len(rows)}.npy"
                env = {**os.environ, "FLAMENERF_GPU_KERNELS": chosen,
                       "PYTHONUNBUFFERED": "1"}
                if args.device == "cpu":
                    env.update(TRITON_INTERPRET="1", FLAMENERF_CPU_KERNELS="0")
                t = time.perf_counter()
                try:
                    p = subprocess.run([sys.executable, __file__, "--child", "--device",
                                        args.device, "--preset", args.preset, "--size",
                                        str(size), "--save", save]
                                       + (["--heads", heads] if heads else []), env=env,
                                       capture_output=True, text=True, timeout=args.timeout)
                    rc, err = p.returncode, (p.stderr or "").strip().splitlines()
                except subprocess.TimeoutExpired:
                    rc, err = "timeout", []
                row = {"size": size, "kernels": label, "env": chosen, "heads": heads, "rc": rc,
                       "seconds": round(time.perf_counter() - t, 1)}
                if rc == 0:
                    img = np.load(save)
                    if ref is None and chosen == "0":
                        ref = img
                    if ref is not None:
                        d = np.abs(img - ref)
                        row["max_abs_diff"] = float(d.max())
                        row["nan"] = int(np.isnan(img).sum())
                else:
                    row["error"] = next((ln for ln in reversed(err) if "Error" in ln),
                                        err[-1] if err else "")[:300]
                rows.append(row)
                print(f"{size:4d}px  {label:>20s}  rc {rc!s:>7}  {row['seconds']:6.1f} s  "
                      + (f"max |diff| {row['max_abs_diff']:.4f}" if "max_abs_diff" in row
                         else row.get("error", "")), flush=True)
    if args.json:
        args.json.write_text(json.dumps({"command": " ".join(sys.argv), "rows": rows},
                                        indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
