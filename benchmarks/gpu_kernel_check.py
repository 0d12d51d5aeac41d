"""Which Triton kernel fails or differs on this GPU: one frame of an untrained preset
rendered down the inference path with the kernels off, then all on, today's default and
the field heads as they were before 2026-11-28 (widths of 16); where any of those fails,
each kernel alone and all but each. Every render runs in a fresh process (a fault ends
the CUDA context) and is compared with the kernels-off render. Prints a table, writes
JSON, and with --keep writes the largest set of kernels that rendered right, as
FLAMENERF_GPU_KERNELS takes it (benchmarks/gpu_targets.sh renders with that set).

    python benchmarks/gpu_kernel_check.py --device cuda --sizes 128 --json check.json

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
sys.path.insert(0, str(HERE.parent / "src"))
from flamenerf.workflows.kernel_check import (  # noqa: E402
    BISECT, FIRST, RIGHT, best_set)


def child(args) -> None:
    import contextlib

    import numpy as np
    import torch

    from flamenerf import gpu_kernels
    from flamenerf.model.inference import FAST
    from flamenerf.model.render_image import render_image
    from flamenerf.workflows.untrained import camera, untrained

    if args.heads:  # BLOCK,WARPS[,DOT_MIN]
        h = [int(v) for v in args.heads.split(",")]
        gpu_kernels.HEADS_BLOCK, gpu_kernels.HEADS_WARPS = h[:2]
        if len(h) > 2:
            gpu_kernels.DOT_MIN = h[2]
    dev = torch.device(args.device)
    m = untrained(args.preset, dev)
    w, a = m.codes(torch.tensor([0], device=dev))
    intr, c2w = camera(args.size)
    mask = np.zeros((args.size, args.size), bool)
    mask[args.size // 4: 3 * args.size // 4, args.size // 3: 2 * args.size // 3] = True
    if dev.type == "cpu":
        from flamenerf.model.gpu_emulation import gpu_path_on_cpu
        ctx = gpu_path_on_cpu(half=True)
    else:
        ctx = contextlib.nullcontext()
    with ctx:
        out = render_image(m, intr, c2w, w[0].detach(), a[0].detach(),
                           torch.full((m.expr_dim,), 0.3), mask, settings=FAST)
        if dev.type == "cuda":
            torch.cuda.synchronize(dev)
    np.save(args.save, out["rgb"].float().cpu().numpy())


def render(args, tmp: str, size: int, label: str, chosen: str, heads: str, n: int) -> dict:
    """One configuration's frame in a fresh process -> its row (the image saved)."""
    save = f"{tmp}/{size}_{n}.npy"
    env = {**os.environ, "FLAMENERF_GPU_KERNELS": chosen, "PYTHONUNBUFFERED": "1"}
    if not chosen:
        del env["FLAMENERF_GPU_KERNELS"]
    if args.device == "cpu":
        env.update(TRITON_INTERPRET="1", FLAMENERF_CPU_KERNELS="0")
    t = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, __file__, "--child", "--device", args.device,
                            "--preset", args.preset, "--size", str(size), "--save", save]
                           + (["--heads", heads] if heads else []), env=env,
                           capture_output=True, text=True, timeout=args.timeout)
        rc, err = p.returncode, (p.stderr or "").strip().splitlines()
    except subprocess.TimeoutExpired:
        rc, err = "timeout", []
    row = {"size": size, "kernels": label, "env": chosen, "heads": heads, "rc": rc,
           "seconds": round(time.perf_counter() - t, 1), "save": save}
    if rc != 0:
        row["error"] = next((ln for ln in reversed(err) if "Error" in ln),
                            err[-1] if err else "")[:300]
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--sizes", type=int, nargs="+", default=[128])
    ap.add_argument("--timeout", type=float, default=180.0, help="seconds per render")
    ap.add_argument("--bisect", choices=("on-failure", "always", "never"),
                    default="on-failure", help="each kernel alone and all but each")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--keep", type=Path,
                    help="write the largest set of kernels that rendered right here")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--size", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--save", help=argparse.SUPPRESS)
    ap.add_argument("--heads", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args)
        return 0
    import tempfile

    import numpy as np

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes:
            ref, failed, bisected, todo = None, False, False, list(FIRST)
            while todo:
                label, chosen, heads = todo.pop(0)
                row = render(args, tmp, size, label, chosen, heads, len(rows))
                if row["rc"] == 0:
                    img = np.load(row["save"])
                    if chosen == "0":
                        ref = img
                    row["nan"] = int(np.isnan(img).sum())
                    row["max_abs_diff"] = float(np.nan_to_num(np.abs(img - ref), nan=1.0)
                                                .max()) if ref is not None else None
                row["right"] = (row["rc"] == 0 and row["max_abs_diff"] is not None
                                and row["max_abs_diff"] < RIGHT and not row["nan"])
                del row["save"]
                rows.append(row)
                save(args, rows)
                print(f"{size:4d}px  {label:>26s}  rc {row['rc']!s:>7}  {row['seconds']:6.1f} s  "
                      + (f"max |diff| {row['max_abs_diff']:.4f}"
                         if row.get("max_abs_diff") is not None else row.get("error", "")),
                      flush=True)
                if chosen == "0" and ref is None:
                    print("the kernels-off render failed: nothing to compare with", flush=True)
                    break
                failed |= not row["right"] and not heads
                if not todo and not bisected and (args.bisect == "always"
                                                  or args.bisect == "on-failure" and failed):
                    todo, bisected = list(BISECT), True
    keep = save(args, rows)
    print(f"kernels that rendered right at every size: FLAMENERF_GPU_KERNELS={keep}")
    return 0


def save(args, rows: list[dict]) -> str:
    """The JSON and the kept set as they stand (after every render: a check stopped by a
    time limit leaves what it found) -> the kept set."""
    keep = best_set(rows)
    if args.keep:
        args.keep.write_text(keep + "\n")
    if args.json:
        args.json.write_text(json.dumps({"command": " ".join(sys.argv), "right_below": RIGHT,
                                         "keep": keep, "rows": rows}, indent=1))
    return keep


if __name__ == "__main__":
    raise SystemExit(main())
