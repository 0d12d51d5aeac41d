"""Time `flamenerf synth` (default: 256 x 256, 300 capture frames + reanimate + leakage).

Prints a summary and writes JSON (default docs/bench/synth.json) with wall
time, CPU time (this process and its render workers), frames per second, and the load
average before and after: other processes on the machine slow the run down, so read the
wall time together with the load.

Usage: python benchmarks/bench_synth.py [--size 256] [--frames 300] [--workers 0]
        [--json docs/bench/synth.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=0, help="0: one per CPU core (at most 4)")
    ap.add_argument("--json", type=Path, default=Path("docs/bench/synth.json"))
    ap.add_argument("--keep", type=Path, default=None, help="keep the dataset here")
    args = ap.parse_args()

    from flamenerf.synthetic.scene import frame_specs, make_scene

    n_frames = len(frame_specs(args.seed, args.frames, 1.0))
    tmp = Path(tempfile.mkdtemp(prefix="bench_synth_"))
    dest = args.keep or tmp / "scene"
    load_before = os.getloadavg()
    usage = lambda: (resource.getrusage(resource.RUSAGE_SELF),  # noqa: E731
                     resource.getrusage(resource.RUSAGE_CHILDREN))
    r0s, r0c = usage()
    t0 = time.perf_counter()
    try:
        make_scene(dest, seed=args.seed, size=args.size, frames=args.frames, overwrite=True,
                   workers=args.workers)
    finally:
        wall = time.perf_counter() - t0
        if args.keep is None:
            shutil.rmtree(tmp, ignore_errors=True)
    r1s, r1c = usage()
    cpu = sum(getattr(b, f) - getattr(a, f) for a, b in ((r0s, r1s), (r0c, r1c))
              for f in ("ru_utime", "ru_stime"))
    result = {
        "benchmark": "synth",
        "size": args.size,
        "capture_frames": args.frames,
        "total_frames": n_frames,
        "workers": args.workers,
        "wall_s": round(wall, 2),
        "cpu_s": round(cpu, 2),
        "frames_per_s": round(n_frames / wall, 3),
        "cpu_ms_per_frame": round(1000 * cpu / n_frames, 1),
        "cpu_count": os.cpu_count(),
        "loadavg_before": [round(x, 2) for x in load_before],
        "loadavg_after": [round(x, 2) for x in os.getloadavg()],
        "python": platform.python_version(),
        "torch": __import__("torch").__version__,
    }
    print(f"synth {args.size}x{args.size}, {n_frames} frames ({args.frames} capture): "
          f"{wall:.1f} s wall, {cpu:.1f} s CPU ({1000 * cpu / n_frames:.0f} ms/frame), "
          f"load average before {load_before[0]:.2f}")
    args.json.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.json.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=1) + "\n")
    os.replace(tmp, args.json)
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
