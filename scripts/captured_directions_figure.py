"""Re-animation frames of a run rendered with the view direction as asked and as the
capture saw it (data/captured_views.py), beside the ground truth.

    python scripts/captured_directions_figure.py RUN [--dataset D] [--frames 0 1]
        [--out docs/captured_directions.png]

Rows: the dataset's `reanimate` split frames (novel cameras and expressions, frame 0's
codes); columns: ground truth | direction as asked | captured directions.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--dataset", type=Path, default=None)
    ap.add_argument("--split", default="reanimate")
    ap.add_argument("--frames", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--scale", type=int, default=2, help="pixel repetition of the figure")
    ap.add_argument("--out", type=Path, default=Path("docs/captured_directions.png"))
    args = ap.parse_args()
    from flamenerf.data.scene import FrameSet
    from flamenerf.evaluation.protocol import render_frames
    from flamenerf.images import hstack, vstack
    from flamenerf.io import save_png
    from flamenerf.training.run import load_run

    run = load_run(args.run, "cpu")
    ds = run.dataset(args.dataset)
    frames = [ds.split(args.split)[i] for i in args.frames]
    fs = FrameSet(ds, frames, run.train_intrinsics(ds))
    om, ph = run.frame_codes(0)
    cols = [[np.asarray(fs.images[i]) for i in range(fs.n)]]
    for captured in (False, True):
        run.attach(ds, captured)
        with torch.no_grad():
            cols.append(render_frames(run.model, fs, om.expand(fs.n, -1),
                                      ph.expand(fs.n, -1), 16384))
    rows = [hstack([c[i] for c in cols]) for i in range(fs.n)]
    img = vstack(rows).repeat(args.scale, 0).repeat(args.scale, 1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_png(args.out, img)
    print(f"wrote {args.out}: ground truth | direction as asked | captured directions")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
