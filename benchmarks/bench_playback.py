"""What the viewer shows while a track plays or a slider is dragged: images per second and
their heights.

Starts the viewer on RUN (no browser: the render worker's display callback counts the
images a page would get), points one view at frame 0's camera with a 16:9 page, picks the
capture track and plays it for `--seconds`, As filmed (each frame's own codes, head pose and
mesh) and not (frame 0's codes); then drags the slider of the control the training frames
move most across its range and back for as long, 20 updates a second (what viser's page
sends at most), and writes what it counted.

    python benchmarks/bench_playback.py RUN [--seconds 8] [--resolution 128] [--threads 2]
        [--json OUT.json]
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import socket
import sys
import time
from pathlib import Path


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    from flamenerf.runtime import set_threads
    from flamenerf.training.run import load_run
    from flamenerf.viewer.app import Viewer
    from flamenerf.viewer.options import ViewerOptions

    set_threads(args.threads)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    v = Viewer(load_run(args.run, "cpu"), ViewerOptions(port=port, resolution=args.resolution,
                                                        verbose=False)).start()
    shown: list[tuple[float, int]] = []
    v.worker.display = lambda key, f: shown.append((time.monotonic(), f.intr.h))
    res: dict = {"benchmark": "playback", "command": "python benchmarks/bench_playback.py "
                 + " ".join(sys.argv[1:]), "cpu_count": os.cpu_count(),
                 "threads": args.threads, "seconds": args.seconds, "modes": {}}
    try:
        v.worker.set_camera("page", v.home.c2w, v.home.fov_y, 16 / 9)
        v.worker.wait_idle(120)
        capture = next((t for t in v.tracks if t.name.startswith("capture")), None)
        if capture is None:
            print(f"{args.run}: its dataset has no capture track", file=sys.stderr)
            return 1
        v.g_track.value = capture.name
        res["track"], res["fps"] = capture.name, capture.fps
        box = getattr(v, "g_filmed", None)  # None: not the clip's frames (or older code)
        for filmed in (True, False) if box is not None else (False,):
            if box is not None:
                v.g_filmed.value = filmed
            v.worker.wait_idle(120)
            n, t0 = len(shown), time.monotonic()
            v.play()
            time.sleep(args.seconds)
            v.pause()
            got = [h for t, h in shown[n:] if t - t0 <= args.seconds]
            mode = "as filmed" if filmed else "frame 0's codes"
            res["modes"][mode] = {"images": len(got),
                                  "images_per_s": round(len(got) / args.seconds, 2),
                                  "heights": dict(collections.Counter(got))}
            print(f"{mode}: {len(got)} images in {args.seconds:g} s "
                  f"({len(got) / args.seconds:.1f}/s), heights {dict(collections.Counter(got))}",
                  flush=True)
            v.worker.wait_idle(120)
        import numpy as np

        x = v.ds.expression_matrix(v.ds.frames)
        j = int(np.argmax(x.max(0) - x.min(0)))
        lo, hi = float(x[:, j].min()), float(x[:, j].max())
        v.set_expression(v.frame0_expression)
        v.worker.wait_idle(120)
        n, t0 = len(shown), time.monotonic()
        while (t := time.monotonic() - t0) < args.seconds:
            u = abs(((t / 2) % 2) - 1)  # across the range in 2 s and back
            v.worker.set_expression_value(j, lo + (hi - lo) * (1 - u))
            time.sleep(0.05)
        got = [h for t, h in shown[n:] if t - t0 <= args.seconds]
        res["modes"]["slider drag"] = {"control": v.names[j], "images": len(got),
                                       "images_per_s": round(len(got) / args.seconds, 2),
                                       "heights": dict(collections.Counter(got))}
        print(f"slider drag ({v.names[j]}): {len(got)} images in {args.seconds:g} s "
              f"({len(got) / args.seconds:.1f}/s), heights {dict(collections.Counter(got))}",
              flush=True)
    finally:
        v.stop()
    if args.json is not None:
        args.json.write_text(json.dumps(res, indent=1) + "\n")
        print("wrote", args.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
