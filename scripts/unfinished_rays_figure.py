"""Re-animation frames of a run with and without the second pass over rays that the
proposal's samples leave unfinished (`SamplerConfig.refine_main`), beside the ground truth.

    python scripts/unfinished_rays_figure.py RUN [--dataset D] [--frames 4 7] \
        [--scale 2] [--out unfinished_rays.png]

Rows: the chosen frames of the dataset's `reanimate` split (frame 0's codes, the frame's
camera and β, as `eval` renders them); columns: the render with one pass, the same with
the rays it leaves unfinished (opacity below 1 − `refine_below`) in magenta, the render
with the second pass (which takes those of them that the proposal says end), the ground
truth. Rendered with the reference renderer, as `eval` measures.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--dataset", type=Path, default=None)
    ap.add_argument("--frames", type=int, nargs="+", default=[4])
    ap.add_argument("--scale", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("unfinished_rays.png"))
    a = ap.parse_args()

    from flamenerf.data.scene import FrameSet
    from flamenerf.images import hstack, vstack
    from flamenerf.io import save_png
    from flamenerf.model.render_image import render_image
    from flamenerf.training.run import load_run

    run = load_run(a.run, "cpu")
    ds = run.dataset(a.dataset)
    fs = FrameSet(ds, ds.split("reanimate"), run.train_intrinsics(ds))
    w0, p0 = run.frame_codes(0)
    sampler = run.model.cfg.sampler
    refine = sampler.refine_main
    if sampler.kind != "proposal" or refine <= 0:
        raise SystemExit(f"{a.run}: its sampler has no second pass (proposal sampler with "
                         "refine_main > 0)")
    rows = []
    for i in a.frames:
        if not 0 <= i < fs.n:
            raise SystemExit(f"--frames: {i} is not a re-animation frame (0-{fs.n - 1})")
        outs = []
        for n in (0, refine):
            sampler.refine_main = n
            outs.append(render_image(run.model, fs.intr, fs.c2w[i], w0, p0, fs.expressions[i],
                                     fs.masks[i], head=fs.head_of(i)))
        once, twice = (o["rgb"].numpy() for o in outs)
        marked = once.copy()
        marked[outs[0]["acc"].numpy() < 1.0 - sampler.refine_below] = (1.0, 0.0, 1.0)
        rows.append(hstack([once, marked, twice, fs.images[i].numpy()], gap=2))
    sampler.refine_main = refine
    img = vstack(rows, gap=2)
    img = np.kron(img, np.ones((a.scale, a.scale, 1), img.dtype))
    save_png(a.out, img.clip(0, 1))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
