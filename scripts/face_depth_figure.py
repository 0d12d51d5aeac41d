"""The rendered face's depth with and without the face-depth prior (docs/face_depth.png).

    python scripts/face_depth_figure.py OUT.png SPLIT RUN [RUN ...]

Two frames of SPLIT (e.g. `reanimate`), each rendered as a re-animation (frame 0's codes,
the frame's camera and β): a row of colour (ground truth, then each run) and a row of
depth on one colour scale spanning the face (the dataset's depth where it has one at the
run's resolution, else the face mesh's, then each run's).
"""

from __future__ import annotations

import sys

import numpy as np


def main(argv: list[str]) -> None:
    from flamenerf.data.scene import FrameSet
    from flamenerf.images import colorize_depth, hstack, vstack
    from flamenerf.io import save_png
    from flamenerf.model.render_image import render_image
    from flamenerf.training.run import load_run

    if len(argv) < 3:
        sys.exit(__doc__)
    out, split, runs = argv[0], argv[1], [load_run(r, "cpu") for r in argv[2:]]
    ds = runs[0].dataset()
    intr = runs[0].train_intrinsics(ds)
    frames = ds.split(split)
    fs = FrameSet(ds, [frames[0], frames[len(frames) // 2]], intr)
    rows = []
    for i in range(fs.n):
        fr = fs.frames[i]
        gt_depth = ds.load_depth(fr)
        if gt_depth is None or gt_depth.shape != (intr.h, intr.w):  # a tracked clip's: its mesh
            gt_depth = fs.mesh_depths()[i].numpy()
        face = fs.masks[i].numpy()
        lo, hi = np.percentile(gt_depth[face & np.isfinite(gt_depth)], [1, 99])
        lo, hi = lo - 0.03, hi + 0.03
        rgb, depth = [fs.images[i].numpy()], [colorize_depth(gt_depth, lo, hi)]
        for run in runs:
            w0, p0 = run.frame_codes(0)
            r = render_image(run.model, intr, fs.c2w[i], w0, p0, fs.expressions[i],
                             fs.masks[i], head=fs.head_of(i))
            rgb.append(r["rgb"].numpy())
            depth.append(colorize_depth(r["depth"].numpy(), lo, hi))
        rows += [hstack(rgb, gap=2), hstack(depth, gap=2)]
    save_png(out, np.clip(vstack(rows, gap=2), 0, 1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main(sys.argv[1:])
