"""Quality per step of config variants (used on a GPU to compare `fast` variants quickly).

    python benchmarks/sweep_variants.py VARIANTS.json OUT.jsonl

VARIANTS.json is a list of {"name": ..., "over": "python statements on `cfg`",
"preset": "fast" (default), "evals": [steps at which to evaluate on the way]}, e.g.
[{"name": "main48", "over": "cfg.model.sampler.num_main=48"}]. Each variant trains for its
schedule's steps on `$SCENE` (default scenes/s128, made if missing) and reports held-out
PSNR on 6 val frames (ω fitted 100 steps; `bench_train.heldout_psnr`) and the PSNR of 3
training frames rendered with their own codes; one JSON line per variant is appended to
OUT.jsonl. Wall time on the machine at hand is recorded, but compare variants' CPU cost
with `bench_train.py` on the CPU itself.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    from bench_train import heldout_psnr

    from flamenerf.config import preset
    from flamenerf.data.scene import FrameSet
    from flamenerf.model.render_image import render_image
    from flamenerf.training.trainer import Trainer

    variants, out = json.load(open(sys.argv[1])), sys.argv[2]
    scene = Path(os.environ.get("SCENE", "scenes/s128"))
    if not (scene / "transforms.json").exists():
        from flamenerf.synthetic.scene import make_scene

        make_scene(scene, size=128, frames=300)
    for v in variants:
        torch.manual_seed(0)
        cfg = preset(v.get("preset", "fast"))
        cfg.train.image_every = 0
        exec(v["over"], {"cfg": cfg})
        t = Trainer(cfg, scene, Path(tempfile.mkdtemp()) / "run", quiet=True)
        sub = t.ds.split("val")[::5][:6]
        t0, curve = time.perf_counter(), []
        while t.step < cfg.train.steps:
            t.train_step()
            if t.step in v.get("evals", []):
                p = heldout_psnr(t.model, t.ds, t.intr, sub, 100, 2048)[1]
                curve.append((t.step, round(p, 2)))
        secs = time.perf_counter() - t0
        fs = FrameSet(t.ds, t.ds.split("train")[::90][:3], t.intr)
        t.model.eval()
        om, ph = t.model.codes(fs.frame_index.to(t.device))
        errs = [float(((render_image(t.model, t.intr, fs.c2w[i], om[i], ph[i],
                                     fs.expressions[i], fs.masks[i])["rgb"]
                        - fs.images[i]) ** 2).mean()) for i in range(fs.n)]
        p = heldout_psnr(t.model, t.ds, t.intr, sub, 100, 2048)[1]
        r = dict(name=v["name"], steps=t.step, seconds=round(secs, 1),
                 train3=round(-10 * np.log10(np.mean(errs)), 2), val6=round(p, 2),
                 curve=curve, over=v["over"])
        print("RESULT", json.dumps(r), flush=True)
        with open(out, "a") as f:
            f.write(json.dumps(r) + "\n")


if __name__ == "__main__":
    main()
