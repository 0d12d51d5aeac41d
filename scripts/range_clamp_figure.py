"""Keyframes past the training range, rendered as given and clamped (docs/real_range_clamp.png).

    python scripts/range_clamp_figure.py RUN OUT.png [KEYFRAME ...]

One row per keyframe at frame 0's camera and codes: frame 0's expression | the keyframe as
given (`render --extrapolate`) | clamped to the training frames' range (`render`'s
default). Both with the keyframe's companions where the dataset has them, as `render` does.
"""

from __future__ import annotations

import sys

import numpy as np

DEFAULT = ["mouthSmileLeft=1,mouthSmileRight=1", "browInnerUp=1",
           "eyeWideLeft=1,eyeWideRight=1"]


def main(argv: list[str]) -> None:
    from PIL import Image

    from flamenerf.data.companions import dataset_companions
    from flamenerf.data.expression_range import training_range
    from flamenerf.evaluation.control import reference_renderer
    from flamenerf.images import hstack, to_uint8, vstack
    from flamenerf.rendering.expressions import parse_keyframe
    from flamenerf.training.run import load_run

    if len(argv) < 2:
        sys.exit(__doc__)
    run = load_run(argv[0], "cpu")
    ds = run.dataset()
    names = run.expression_names
    omega0, phi0 = run.frame_codes(0)
    render, fr, _ = reference_renderer(run.model, ds, run.train_intrinsics(ds), omega0, phi0)
    base = ds.expression_matrix([fr])[0]
    comp, rng = dataset_companions(ds), training_range(ds)
    rows = []
    for item in argv[2:] or DEFAULT:
        given = parse_keyframe(item, names, base, comp)
        rows.append(hstack([render(base), render(given), render(rng.clamp(given))], gap=2))
        print(f"{item}: {'; '.join(rng.beyond(given)) or 'within the range'}")
    img = vstack(rows, gap=2)
    img = to_uint8(img) if img.dtype != np.uint8 else img
    h, w = img.shape[:2]
    Image.fromarray(img).resize((2 * w, 2 * h), Image.NEAREST).save(argv[1])
    print(f"wrote {argv[1]}")


if __name__ == "__main__":
    main(sys.argv[1:])
