"""Render (or training-step) speed of two or more source trees side by side, for machines
whose speed drifts.

On a shared machine the same frame's time drifts by up to ~35 % between runs minutes apart,
so a before/after figure from two separate `bench_render.py` runs says little. This script
times one frame of a trained run with each source tree (`--src`, e.g. a `git worktree` of the
old commit and this checkout) in fresh processes, alternating them for `--rounds` rounds, and
reports each tree's best and median time per size. With `--train PRESET` it times training
steps instead: a fresh run of that preset on `--dataset` at its training size, half-way
through its schedule (every loss term on), after two warm-up steps.

    git worktree add /tmp/old HEAD~1
    python benchmarks/bench_render_ab.py --run RUN --dataset SCENE --src /tmp/old/src src \
        --json docs/bench/render_ab.json
    python benchmarks/bench_render_ab.py --train fast --dataset SCENE --src /tmp/old/src src
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np

from flamenerf.runtime import TUNED_ALLOCATOR

# one process: load the run, render frame 0's view at each size (warm-up, then `repeats`)
_CHILD = r"""
import json, sys, time
import numpy as np, torch
torch.set_num_threads(int(sys.argv[3]))
from flamenerf.training.run import load_run
from flamenerf.model.render_image import render_image
from flamenerf.model import inference
SETTINGS = getattr(inference, sys.argv[6])
from flamenerf.data.prior import dataset_dilation, mesh_function, prior_mask
dev = sys.argv[7]
sync = torch.cuda.synchronize if dev.startswith("cuda") else (lambda: None)
run = load_run(sys.argv[1], dev)
ds = run.dataset(sys.argv[2] or None)
fr = [f for f in ds.frames if f.frame_index == 0][0]
omega, phi = run.frame_codes(0)
beta = np.asarray(fr.expression, np.float32)
out = {}
for size in json.loads(sys.argv[4]):
    intr = ds.intrinsics.scaled(size / ds.intrinsics.w)
    mask = prior_mask(ds, mesh_function(run.model, ds)(beta), fr.c2w, intr, dataset_dilation(ds))
    args = (run.model, intr, fr.c2w, omega, phi, torch.as_tensor(beta), mask)
    render_image(*args, settings=SETTINGS)
    ts = []
    for _ in range(int(sys.argv[5])):
        sync()
        t = time.perf_counter()
        render_image(*args, settings=SETTINGS)
        sync()
        ts.append(time.perf_counter() - t)
    out[str(size)] = ts
print(json.dumps(out))
"""

# one process: `repeats` training steps of a fresh run of a preset, half-way through its
# schedule, after two warm-up steps
_TRAIN_CHILD = r"""
import json, sys, tempfile, time
from flamenerf.config import preset
from flamenerf.training.trainer import Trainer
cfg = preset(sys.argv[6])
cfg.train.num_threads = int(sys.argv[3])
cfg.train.image_every = cfg.train.checkpoint_every = 10**9
with tempfile.TemporaryDirectory() as d:
    tr = Trainer(cfg, sys.argv[2], d, quiet=True)
    tr.step = cfg.train.steps // 2
    for _ in range(2):
        tr.train_step()
    ts = []
    for _ in range(int(sys.argv[5])):
        t = time.perf_counter()
        tr.train_step()
        ts.append(time.perf_counter() - t)
print(json.dumps({"step": ts}))
"""


def _label(key: str) -> str:
    return f"{key} px" if key.isdigit() else key


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, default=None, help="a trained run (render speed)")
    ap.add_argument("--train", default=None, metavar="PRESET",
                    help="time training steps of this preset on --dataset instead")
    ap.add_argument("--dataset", type=Path, default=None)
    ap.add_argument("--src", nargs="+", required=True, metavar="SRC",
                    help="source trees (folders holding the flamenerf package), two or more")
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=4)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--settings", choices=["FAST", "VIEWER"], default="FAST",
                    help="render's settings, or the viewer's (model/inference.py)")
    ap.add_argument("--untuned", action="store_true",
                    help="glibc as a library user's process has it (not tuned as the "
                         "`flamenerf` command tunes it)")
    ap.add_argument("--device", default="cpu", help="where the run renders (e.g. cuda); render timing only")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    if (a.run is None) == (a.train is None) or (a.train and a.dataset is None):
        ap.error("give --run RUN (render), or --train PRESET with --dataset")
    if len(a.src) < 2:
        ap.error("give two or more --src trees")
    child, what = ((_TRAIN_CHILD, a.train) if a.train else (_CHILD, a.settings))
    times: dict[str, dict[str, list[float]]] = {s: {} for s in a.src}
    for r in range(a.rounds):
        for src in a.src:
            # glibc tuned as `flamenerf` tunes it (runtime.py), the tree under test first
            env = dict(os.environ, PYTHONPATH=str(Path(src).resolve()))
            if a.untuned:
                for k in TUNED_ALLOCATOR:
                    env.pop(k, None)
            else:
                env.update(TUNED_ALLOCATOR)
            proc = subprocess.run(
                [sys.executable, "-c", child, str(a.run), str(a.dataset or ""),
                 str(a.threads), json.dumps(a.sizes), str(a.repeats), what, a.device],
                env=env, capture_output=True, text=True)
            if proc.returncode:  # one tree that fails (a kernel fault) leaves the others timed
                last = (proc.stderr.strip().splitlines() or ["no output"])[-1]
                print(f"round {r + 1} {src}: failed ({last})", flush=True)
                continue
            got = json.loads(proc.stdout.strip().splitlines()[-1])
            for size, ts in got.items():
                times[src].setdefault(size, []).extend(ts)
            print(f"round {r + 1} {src}: " + ", ".join(
                f"{_label(s)} {min(ts):.4f} s" for s, ts in got.items()), flush=True)
    res = {"benchmark": "train_ab" if a.train else "render_ab",
           "settings": a.train or a.settings,
           "allocator": "glibc default" if a.untuned else "tuned (runtime.TUNED_ALLOCATOR)",
           "command": "python benchmarks/bench_render_ab.py "
           + " ".join(sys.argv[1:]), "machine": f"{platform.processor() or platform.machine()}, "
           f"{os.cpu_count()} cores, {a.threads} threads, device {a.device}", "results": {}}
    for src, per in times.items():
        if not per:
            res["results"][src] = "failed"
            continue
        res["results"][src] = {s: {"best_s": round(min(ts), 4), "median_s":
                                   round(float(np.median(ts)), 4), "n": len(ts)}
                               for s, ts in per.items()}
        for s, v in res["results"][src].items():
            print(f"{src}: {_label(s)} best {v['best_s']:.4f} s, median {v['median_s']:.4f} s "
                  f"({v['n']})")
    if a.json is not None:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(res, indent=1) + "\n")
        print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
