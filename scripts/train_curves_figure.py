"""Time-to-quality curves of `benchmarks/bench_train.py` runs side by side: held-out PSNR
and the driven re-animation's face PSNR against seconds of training, one line per run
(colour by preset, line style by seed).

    python scripts/train_curves_figure.py A.json B.json ... [--title T] [--out curves.png]

Each JSON is what `bench_train.py --json` writes (its `quality_<preset>` entry); a
`--pick KEY` reads that entry of a combined file instead (e.g. docs/bench/*.json holding
several runs under their own keys). The final figures on every val / reanimate frame are
marked at the end of each line.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def runs(path: Path, picks: list[str]) -> list[dict]:
    """The quality entries in one JSON: bench_train's own file, or the entries `picks`
    names in a combined one."""
    data = json.loads(path.read_text())
    found = []
    for entry in ([data[k] for k in picks if k in data] if picks else [data]):
        found += [v for k, v in entry.items() if k.startswith("quality")]
    return found


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("json", type=Path, nargs="+")
    ap.add_argument("--pick", nargs="*", default=[],
                    help="keys of a combined JSON whose entries are bench_train outputs")
    ap.add_argument("--title", default="")
    ap.add_argument("--out", type=Path, default=Path("train_curves.png"))
    a = ap.parse_args()
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    qs = [q for p in a.json for q in runs(p, a.pick)]
    if not qs:
        raise SystemExit("no bench_train quality entries in the files given")
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    colours = {}
    for q in qs:
        c = colours.setdefault(q["preset"], f"C{len(colours)}")
        style = ["-", "--", ":", "-."][q.get("seed", 0) % 4]
        t = [0.0] + [p["train_seconds"] for p in q["curve"]]
        for ax, key, final in ((axes[0], "psnr", "final_heldout_psnr"),
                               (axes[1], "reanimate_psnr_face", "final_reanimate_psnr_face")):
            ys = [p.get(key) for p in q["curve"]]
            if any(y is None for y in ys):
                continue
            ax.plot(t[1:], ys, style, color=c, marker=".",
                    label=f"{q['preset']} seed {q.get('seed', 0)}")
            if q.get(final) is not None:
                ax.plot([q["train_seconds"]], [q[final]], "o", color=c, mfc="none")
    axes[0].set_title("held-out (ω fitted), 6 val frames; ○ all val frames")
    axes[1].set_title("re-animation, face; ○ all reanimate frames")
    for ax in axes:
        ax.set_xlabel("seconds of training")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("PSNR (dB)")
    axes[0].legend(fontsize=8)
    if a.title:
        fig.suptitle(a.title, fontsize=10)
    fig.tight_layout()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(a.out, dpi=100)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
