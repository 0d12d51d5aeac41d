"""Chosen controls swept over the span the training frames cover, for one or more runs of
the same dataset, side by side: what `eval`'s control sweep renders (the reference frame's
camera and codes, the control's companions moving with it), for the controls you name.

    python scripts/control_sweep_figure.py RUN_A RUN_B --controls browInnerUp jawOpen \
        [--steps 5] [--alone] [--full-range] [--crop 0.2 0.6] [--out control_sweep_runs.png]

Rows: each control, then each run within it (run order as given); columns: low to high,
over the control's 5th-95th percentile in the training frames (eval's sweep) or, with
`--full-range`, its smallest to largest value (what the clamp lets a user command).
`--crop A B` keeps the image rows from fraction A to B of the height (e.g. the brows).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def _command(base: np.ndarray, k: int, value: float, companions) -> np.ndarray:
    """base β with control k at `value`, its companions moving along where given."""
    if companions is not None:
        return companions.complete(base, {k: value})
    b = base.copy()
    b[k] = value
    return b


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--dataset", type=Path, default=None)
    ap.add_argument("--controls", nargs="+", required=True)
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--alone", action="store_true", help="without the companions")
    ap.add_argument("--full-range", action="store_true",
                    help="sweep from the smallest to the largest training value")
    ap.add_argument("--crop", type=float, nargs=2, default=(0.0, 1.0), metavar=("A", "B"))
    ap.add_argument("--scale", type=int, default=2, help="pixel repetition of the figure")
    ap.add_argument("--out", type=Path, default=Path("control_sweep_runs.png"))
    args = ap.parse_args()
    import imageio.v3 as iio

    from flamenerf.data.companions import dataset_companions
    from flamenerf.data.dataset import reference_position
    from flamenerf.evaluation import control as C
    from flamenerf.images import hstack, vstack
    from flamenerf.training.run import load_run

    rows: dict[str, list[np.ndarray]] = {c: [] for c in args.controls}
    for path in args.runs:
        run = load_run(path, "cpu")
        ds = run.dataset(args.dataset)
        names = run.expression_names
        omega, phi = run.frame_codes(ds.frames[reference_position(ds)].frame_index)
        render, ref, _ = C.reference_renderer(run.model, ds, run.train_intrinsics(ds), omega,
                                              phi)
        base = ds.expression_matrix([ref])[0]
        train = ds.expression_matrix(ds.split("train"))
        comp = None if args.alone else dataset_companions(ds)
        for c in args.controls:
            if c not in names:
                raise SystemExit(f"{path}: no control named {c}")
            k = names.index(c)
            vals = (np.linspace(train[:, k].min(), train[:, k].max(), args.steps)
                    if args.full_range else C.sweep_values(train[:, k], args.steps))
            if vals is None or np.ptp(vals) == 0:
                raise SystemExit(f"{path}: {c} barely varies in the training frames")

            imgs = [render(_command(base, k, float(v), comp if comp and comp.of(c) else None))
                    for v in vals]
            h = imgs[0].shape[0]
            a, b = (int(round(f * h)) for f in args.crop)
            rows[c].append(hstack([im[a:b] for im in imgs], gap=2))
            print(f"{path} {c}: {vals[0]:.2f} .. {vals[-1]:.2f}", flush=True)
    pic = vstack([r for c in args.controls for r in rows[c]], gap=2).clip(0, 1)
    pic = (pic * 255 + 0.5).astype(np.uint8).repeat(args.scale, 0).repeat(args.scale, 1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(args.out, pic)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
