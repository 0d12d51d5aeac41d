"""Cross-person drives, judged two ways: each run driven by each driving video (`flamenerf
eval RUN --drive VIDEO`), with the relative transfer and with each control's reach matched
(`--drive-match-range`); per pair the correlation over time between the driver and the
re-tracked render, by MediaPipe's blendshape scores (per control the driver moves) and by
the landmark geometry (mouth opening and width, eye opening, brow height).

    python benchmarks/bench_drive.py --runs runs/a runs/b --drivers d1.mp4 d2.mp4 \\
        --out docs/bench/drive_pairs.json

Prints a table and writes the JSON (every pair's figures and the commands that made them).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from flamenerf.io import write_json

BLINKS = ("eyeBlinkLeft", "eyeBlinkRight")


def evaluate(run: Path, driver: Path, matched: bool, out: Path, frames: int,
             threads: int) -> dict:
    cmd = [sys.executable, "-m", "flamenerf.cli", "eval", str(run), "--drive", str(driver),
           "--drive-frames", str(frames), "--fit-steps", "0", "--no-control", "--images", "0",
           "--out", str(out), "--threads", str(threads), "--device", "cpu"]
    if matched:
        cmd.append("--drive-match-range")
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    drive = json.loads((out / "metrics.json").read_text())["drive"]
    controls = {n: c["correlation"] for n, c in drive["controls"].items()}
    geometry = {k: m["correlation"] for k, m in drive["geometry"]["measures"].items()}
    moved = [v for v in controls.values() if v is not None and np.isfinite(v)]
    return {"command": " ".join(cmd[2:]), "seconds": round(time.perf_counter() - t0, 1),
            "controls": controls, "geometry": geometry,
            "mean_correlation": float(np.mean(moved)) if moved else None,
            "jawOpen": controls.get("jawOpen"),
            "blink": (float(np.mean([controls[b] for b in BLINKS if b in controls]))
                      if any(b in controls for b in BLINKS) else None)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=Path, nargs="+", required=True)
    ap.add_argument("--drivers", type=Path, nargs="+", required=True)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--work", type=Path, default=Path("bench_drive_work"))
    ap.add_argument("--out", type=Path, default=Path("bench_drive.json"))
    a = ap.parse_args()
    rows = []
    for run in a.runs:
        for driver in a.drivers:
            for matched in (False, True):
                tag = f"{run.name}_{driver.stem}_{'matched' if matched else 'relative'}"
                r = evaluate(run, driver, matched, a.work / tag, a.frames, a.threads)
                rows.append({"run": str(run), "driver": str(driver),
                             "transfer": "matched" if matched else "relative", **r})
                g = r["geometry"]

                def f(v):
                    return "  -  " if v is None else f"{v:+.2f}"

                print(f"{run.name:>14} <- {driver.stem:<28} {rows[-1]['transfer']:<8} "
                      f"mean {f(r['mean_correlation'])} jaw {f(r['jawOpen'])} "
                      f"blink {f(r['blink'])} | mouth {f(g.get('mouth_open'))} width "
                      f"{f(g.get('mouth_width'))} eyes {f(g.get('eye_open_left'))}/"
                      f"{f(g.get('eye_open_right'))} brows {f(g.get('brow_left'))}/"
                      f"{f(g.get('brow_right'))}", flush=True)
    write_json(a.out, {"rows": rows, "frames": a.frames})
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
