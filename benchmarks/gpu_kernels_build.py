"""Build the GPU path's Triton kernels for NVIDIA GPUs on a machine without one, and say
what each needs: registers per thread, spilled bytes (registers that did not fit, kept in
slow local memory), shared memory, build time.

Time on a GPU is short and rare; a kernel that does not compile for the GPU (Triton's
interpreter, which the tests run, is not its compiler) or that spills would cost it. The
launches are recorded from a real frame: a trained run's view with its most expressive β
(so that every kernel runs; frame 0's codes), rendered small down the GPU's inference
path on this CPU in a child process (model/gpu_emulation.py: Triton's interpreter for the
GPU, CPU autocast in float16 for CUDA's, so the layers' dtypes are a GPU frame's); each
distinct launch is then compiled here for each architecture (flamenerf/gpu_build.py).

Usage: python benchmarks/gpu_kernels_build.py --run RUN [--dataset SCENE] [--arch 80,90]
        [--size 16] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def record(run_dir: Path, dataset: Path | None, size: int) -> list[dict]:
    """The distinct kernel launches of one frame down the GPU's inference path (this
    process must run Triton's interpreter: `main` starts it so)."""
    import torch

    from flamenerf import gpu_kernels
    from flamenerf.model import inference
    from flamenerf.model.gpu_emulation import gpu_path_on_cpu
    from flamenerf.model.render_image import render_image
    from flamenerf.training.run import load_run
    from view_args import view_args

    assert gpu_kernels.available(torch.device("cpu")), "Triton's interpreter is not on"
    run = load_run(run_dir, torch.device("cpu"))
    args = view_args(run, run.dataset(dataset), size, expressive=True)
    settings = dataclasses.replace(inference.FAST, threads=1)
    with gpu_path_on_cpu(half=True), gpu_kernels.recording() as launches:
        render_image(*args, settings=settings)
    distinct = {json.dumps(x, sort_keys=True) for x in launches}
    return [json.loads(x) for x in sorted(distinct)]


def main() -> int:
    from view_args import view_options

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    view_options(ap, size=16, device=None)  # the recorded frame: small, on this CPU
    ap.add_argument("--arch", default="80,90",
                    help="compute capabilities, comma-separated (80: A100, 90: H100/H200)")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--record-to", type=Path, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()

    if a.record_to is not None:  # the child
        a.record_to.write_text(json.dumps(record(a.run, a.dataset, a.size)))
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        rec = Path(tmp) / "launches.json"
        env = {**os.environ, "TRITON_INTERPRET": "1", "FLAMENERF_GPU_KERNELS": "1",
               "FLAMENERF_CPU_KERNELS": "0"}
        cmd = [sys.executable, "-W", "ignore", __file__, "--run", str(a.run), "--size",
               str(a.size), "--record-to", str(rec)]
        if a.dataset is not None:
            cmd += ["--dataset", str(a.dataset)]
        subprocess.run(cmd, env=env, check=True)
        launches = json.loads(rec.read_text())

    # a cache of its own: the times of full builds, not of earlier runs' cache hits
    os.environ["TRITON_CACHE_DIR"] = tempfile.mkdtemp(prefix="flamenerf-triton-")
    import torch
    import triton

    from flamenerf import gpu_build

    assert os.environ.get("TRITON_INTERPRET") != "1", "run without TRITON_INTERPRET"
    rows = []
    for launch in launches:
        shown = {**launch["constexprs"], "num_warps": launch["num_warps"]}
        for arch in (int(x) for x in a.arch.split(",")):
            try:
                got = gpu_build.build(launch, arch)
            except Exception as e:  # noqa: BLE001 - reported: what a GPU would have hit
                got = {"arch": arch, "error": f"{type(e).__name__}: {str(e)[:300]}"}
            rows.append({"kernel": launch["kernel"], "constexprs": launch["constexprs"],
                         "num_warps": launch["num_warps"], "signature": launch["signature"],
                         "divisible": launch["divisible"], **got})
            print(f"{launch['kernel']:12s} sm_{arch} {shown} -> "
                  + (got["error"] if "error" in got else
                     f"{got['registers']} registers, {got['spill_bytes']} bytes spilled, "
                     f"{got['shared_bytes']} bytes shared, built in {got['seconds']} s"),
                  flush=True)
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps({"run": str(a.run), "size": a.size,
                                      "triton": triton.__version__, "torch": torch.__version__,
                                      "builds": rows}, indent=1) + "\n")
    return 1 if any("error" in r for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
