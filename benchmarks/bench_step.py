"""Training-step A/B: one preset's step timed under config variants, alternated in one
process so that the machine's drift touches every variant alike. Prints each variant's
median and best step time and writes JSON.

    python benchmarks/bench_step.py --scene S --threads 2 \
        --variants "fp32:train.bf16=false;bf16:train.bf16=true" --json OUT.json

Each variant gets its own fresh run (in a temporary folder), set to the middle of its
schedule (`--at`, a share of the steps: the warp's coarse-to-fine window and the face-depth
prior then act as they do mid-run), warmed up by `--warmup` steps; then `--rounds` rounds
time `--steps` steps of every variant in turn. The step is `Trainer.train_step` as training
runs it (previews, checkpoints and logging are not part of it). A fresh model's samples do
not fall where a trained one's do (the proposal has not learned where the scene is, so the
head's region holds another share of them): `--run RUN` loads a trained run's weights
(same preset and dataset) into every variant first, and starts at its step.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, required=True, help="a dataset (e.g. `flamenerf synth`'s)")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--variants", default="fast:",
                    help="`name:key=value,...;name2:...` config overrides of the preset")
    ap.add_argument("--at", type=float, default=0.5, help="share of the schedule to start at")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--steps", type=int, default=8, help="steps per variant per round")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: its default)")
    ap.add_argument("--run", type=Path, default=None,
                    help="a trained run of this preset and dataset whose weights to start from")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    from flamenerf.runtime import reexec_with_tuned_allocator

    reexec_with_tuned_allocator([str(Path(__file__).resolve()), *sys.argv[1:]])
    from flamenerf.config import override, parse_variants, preset
    from flamenerf.training.trainer import Trainer

    if a.threads > 0:
        torch.set_num_threads(a.threads)
    tmp = Path(tempfile.mkdtemp(prefix="bench_step_"))
    state = None
    if a.run is not None:
        from flamenerf.training.checkpoint import load_latest

        found = load_latest(a.run)
        if found is None:
            raise SystemExit(f"{a.run}: no checkpoint to start from")
        state = found[1]
    trainers = {}
    for name, values in parse_variants(a.variants):
        cfg = override(preset(a.preset), values)
        cfg.train.image_every = 0
        t = Trainer(cfg, a.scene, tmp / name, quiet=True)
        t.step = int(a.at * cfg.train.steps)
        if state is not None:
            t.model.load_state_dict(state["model"])
            t.step = int(state["step"])
        for _ in range(a.warmup):
            t.train_step()
        trainers[name] = (t, values)
        print(f"{name}: {values or 'the preset'} (train.bf16 settled to {t.cfg.train.bf16})")
    times: dict[str, list[float]] = {n: [] for n in trainers}
    for r in range(a.rounds):
        for name, (t, _) in trainers.items():
            t0 = time.perf_counter()
            for _ in range(a.steps):
                t.train_step()
            times[name].append((time.perf_counter() - t0) / a.steps)
        print(f"round {r + 1}: " + ", ".join(f"{n} {v[-1]:.3f} s" for n, v in times.items()))
    out = {"machine": {"platform": platform.platform(), "processor": platform.processor(),
                       "torch": torch.__version__, "threads": torch.get_num_threads()},
           "scene": str(a.scene), "preset": a.preset, "run": str(a.run) if a.run else None,
           "at": a.at if a.run is None else None, "steps": a.steps,
           "rounds": a.rounds, "variants": {}}
    for name, (t, values) in trainers.items():
        v = times[name]
        out["variants"][name] = {"overrides": values, "bf16": t.cfg.train.bf16,
                                 "batch_rays": t.cfg.train.batch_rays,
                                 "seconds_per_step_median": statistics.median(v),
                                 "seconds_per_step_best": min(v), "rounds": v}
        print(f"{name:12s} median {statistics.median(v):.3f} s/step, best {min(v):.3f}")
    if a.json:
        from flamenerf.io import write_json

        a.json.parent.mkdir(parents=True, exist_ok=True)
        write_json(a.json, out)
        print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
