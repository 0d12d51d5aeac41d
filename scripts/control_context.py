"""Which of a training frame's controls make the landmarker read one control, and does that
reading depend on parts of the face the control does not touch?

    python scripts/control_context.py RUN --frame 132 --control browInnerUp \
        [--without jawOpen] [--out docs/control_context.png]

Renders the run at its reference camera with the reference frame's codes and (1) frame
FRAME's whole β, (2) that β with each control that differs from the reference frame's set
back to the reference value, one at a time, and re-tracks every render with MediaPipe: the
score of CONTROL for each. With `--without NAME` it also prints how much the render changes
above and below the eyes when NAME is set back (the per-control prior keeps a lower-face
control out of the brows), and writes the renders with and without it side by side.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--dataset", type=Path, default=None)
    ap.add_argument("--frame", type=int, required=True, help="a frame index of the dataset")
    ap.add_argument("--control", required=True, help="the control whose reading to explain")
    ap.add_argument("--without", default=None, help="a control to set back, for the picture")
    ap.add_argument("--min-change", type=float, default=0.05,
                    help="controls closer than this to the reference frame's are left alone")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    from flamenerf.data.dataset import reference_position
    from flamenerf.evaluation import control as C
    from flamenerf.geometry import project_points
    from flamenerf.training.run import load_run

    run = load_run(args.run, "cpu")
    ds = run.dataset(args.dataset)
    names = run.expression_names
    ref = ds.frames[reference_position(ds)]
    frame = next((f for f in ds.frames if f.frame_index == args.frame), None)
    if frame is None or args.control not in names:
        raise SystemExit(f"{args.run}: no frame {args.frame} or no control {args.control}")
    intr = run.train_intrinsics(ds)
    omega, phi = run.frame_codes(ref.frame_index)
    render, _, mesh_of = C.reference_renderer(run.model, ds, intr, omega, phi)
    beta, base = ds.expression_matrix([frame])[0], ds.expression_matrix([ref])[0]
    track = C.Retracker()
    try:
        def score(b):
            s = track(render(b))
            return float("nan") if s is None else s[args.control]

        print(f"{args.control} read on renders: frame {args.frame}'s β {score(beta):.3f}, "
              f"the reference frame's {score(base):.3f}")
        rows = []
        for j, n in enumerate(names):
            if abs(beta[j] - base[j]) >= args.min_change:
                b = beta.copy()
                b[j] = base[j]
                rows.append((score(b), n, beta[j], base[j]))
        for v, n, a, r in sorted(rows):
            print(f"  {n} set back ({a:.2f} -> {r:.2f}): {v:.3f}")
        if args.without:
            k = names.index(args.without)
            b = beta.copy()
            b[k] = base[k]
            full, less = render(beta), render(b)
            # above / below the eyes of the frame's mesh, as projected into this camera
            eyes_y = project_points(mesh_of(beta), intr, ref.c2w)[0][[33, 133, 263, 362], 1]
            cut = int(round(eyes_y.mean()))
            d = np.abs(full - less).max(-1)
            print(f"{args.without} set back: largest change above the eyes {d[:cut].max():.4f}, "
                  f"below {d[cut:].max():.4f} (0-1)")
            if args.out is not None:
                import imageio.v3 as iio

                args.out.parent.mkdir(parents=True, exist_ok=True)
                pic = np.concatenate([full, less], 1).clip(0, 1)
                iio.imwrite(args.out, (pic * 255 + 0.5).astype(np.uint8).repeat(2, 0)
                            .repeat(2, 1))
                print(f"wrote {args.out}")
    finally:
        track.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
