"""A contact sheet of a synthetic dataset: train, depth, reanimate and leakage frames with the
face masks tinted.

Usage: python -m flamenerf.synthetic.contact_sheet DATASET OUT.png
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from flamenerf.data.dataset import load_dataset

LEAKAGE_SHOWN = ("neutral", "jawOpen", "mouthSmileLeft", "mouthPucker", "cheekPuff",
                 "mouthFrownRight", "browInnerUp", "browDownLeft", "eyeBlinkRight", "eyeWideLeft")


def _tint(rgb: np.ndarray, mask: np.ndarray, colour=(0.2, 0.45, 1.0), alpha=0.22) -> np.ndarray:
    from scipy import ndimage

    out = rgb.copy()
    out[mask] = (1 - alpha) * out[mask] + alpha * np.asarray(colour)
    edge = mask & ~ndimage.binary_erosion(mask)
    out[edge] = colour
    return out


def contact_sheet(dataset: str | Path, out: str | Path, columns: int = 5) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ds = load_dataset(dataset)

    def pick(frames, n):
        if len(frames) <= n:
            return list(frames)
        return [frames[round(i * (len(frames) - 1) / (n - 1))] for i in range(n)]

    train = pick(ds.split("train"), columns)
    rows: list[tuple[str, list]] = [("train (mask tinted)", [("rgb", f, f"train t={f.frame_index}")
                                                            for f in train])]
    rows.append(("depth", [("depth", f, f"depth t={f.frame_index}") for f in train]))
    if "reanimate" in ds.splits:
        re = pick(ds.split("reanimate"), columns)
        rows.append(("reanimate", [("rgb", f, f"reanimate {i}") for i, f in enumerate(re)]))
    if "leakage" in ds.splits:
        lk = ds.split("leakage")
        best: dict[str, object] = {}
        for f in lk:
            name, val = f.extra.get("leakage_control"), f.extra.get("leakage_value", 0.0)
            if name in LEAKAGE_SHOWN and val >= best.get(name, (None, -1))[1]:
                best[name] = (f, val)
        shown = [best[n] for n in LEAKAGE_SHOWN if n in best]
        for r in range(0, len(shown), columns):
            rows.append(("leakage", [("rgb", f, f"{f.extra['leakage_control']}"
                                      + ("" if v == 0 else f"={v:g}"))
                                     for f, v in shown[r:r + columns]]))
    n_rows = len(rows)
    fig, axes = plt.subplots(n_rows, columns, figsize=(2.2 * columns, 2.35 * n_rows), squeeze=False)
    lo, hi = ds.near, ds.far
    for r, (_, panels) in enumerate(rows):
        for c in range(columns):
            ax = axes[r][c]
            ax.axis("off")
            if c >= len(panels):
                continue
            kind, f, title = panels[c]
            if kind == "rgb":
                img = _tint(ds.load_image(f), ds.load_mask(f))
                ax.imshow(np.clip(img, 0, 1), interpolation="nearest")
            else:
                im = ax.imshow(ds.load_depth(f), cmap="turbo", vmin=lo, vmax=min(hi, 1.6),
                               interpolation="nearest")
            ax.set_title(title, fontsize=8)
        if rows[r][1] and rows[r][1][0][0] == "depth":
            cax = axes[r][-1].inset_axes((1.03, 0.0, 0.06, 1.0))
            cb = fig.colorbar(im, cax=cax)
            cb.set_label("z-depth (m)", fontsize=7)
            cb.ax.tick_params(labelsize=6)
    src = ds.source
    fig.suptitle(f"flamenerf synth --seed {src.get('seed')} --size {src.get('size')} "
                 f"--frames {src.get('frames')}  (blue: face mask)", fontsize=9, y=1.0)
    fig.tight_layout(rect=(0, 0, 1, 0.985))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        print(__doc__.strip().splitlines()[-1], file=sys.stderr)
        return 2
    print(contact_sheet(args[0], args[1]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
