"""Fingerprints of fixed-seed trainings, for refactors that must not change the math:
`fast` (masked, 6 steps), its Nerfies and no-prior variants (3 steps) on a 32 px built-in
scene, and `fast` (4 steps) on a 32 px scene whose head turns; per training a hash of
every saved tensor and of one render (with a head twist on the head scene).

    python benchmarks/weights_fingerprint.py --out before.json   # on the old tree
    python benchmarks/weights_fingerprint.py --out after.json --compare before.json

Prints what differs (nothing: bit-identical) and writes the JSON.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import tempfile
from pathlib import Path

import torch

from flamenerf.config import preset
from flamenerf.data.head_pose import canonical_from_world
from flamenerf.data.scene import FrameSet
from flamenerf.geometry import se3_log
from flamenerf.io import write_json
from flamenerf.model.render_image import render_image
from flamenerf.synthetic.scene import make_scene
from flamenerf.training.trainer import Trainer

# state-dict names of earlier layouts, mapped to today's (the expression pathway's buffers)
RENAMED = {k: f"expression.{k}" for k in ("mesh_neutral", "mesh_basis", "mesh_faces",
                                           "mesh_regions")}


def digest(t: torch.Tensor) -> str:
    return hashlib.sha256(t.detach().cpu().contiguous().numpy().tobytes()).hexdigest()[:16]


def fingerprint(scene: Path, run: Path, mode: str, steps: int, frame: int,
                with_head: bool) -> dict[str, str]:
    cfg = preset("fast")
    cfg.model.expression_mode = mode
    t = cfg.train
    t.steps, t.batch_rays, t.face_reg_points, t.downscale = steps, 256, 64, 1.0
    t.image_every, t.bf16, t.checkpoint_every, t.face_depth_start = 0, False, 10_000, 0.0
    tr = Trainer(cfg, scene, run, device="cpu", quiet=True)
    tr.fit()
    out = {RENAMED.get(k, k): digest(v) for k, v in sorted(tr.model.state_dict().items())}
    fr = tr.ds.frames[frame]
    fs = FrameSet(tr.ds, [fr], tr.intr)
    omega, phi = tr.model.codes(fs.frame_index)
    head = (torch.as_tensor(se3_log(canonical_from_world(tr.ds, [fr]))[0]).float()
            if with_head else None)
    with torch.no_grad(), tr.model.outside_training():
        img = render_image(tr.model, tr.intr, fs.c2w[0], omega[0], phi[0], fs.expressions[0],
                           fs.masks[0], head=head)["rgb"]
    out["__render__"] = digest(img)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--compare", type=Path, default=None)
    a = ap.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        still = make_scene(root / "scene", seed=1, size=32, frames=12, reanimate=2,
                           leakage_steps=1, workers=1)
        head = make_scene(root / "head", seed=2, size=32, frames=8, sway=0.0, reanimate=2,
                          leakage_steps=0, workers=1, head_motion=True)
        res = {}
        for name, scene, mode, steps, frame, with_head in (
                ("fast", still, "masked", 6, 0, False), ("nerfies", still, "none", 3, 0, False),
                ("no-prior", still, "everywhere", 3, 0, False),
                ("fast-head", head, "masked", 4, 3, True)):
            res[name] = fingerprint(scene, root / f"run_{name}", mode, steps, frame, with_head)
            shutil.rmtree(root / f"run_{name}", ignore_errors=True)
    write_json(a.out, res)
    if a.compare is not None:
        before = json.loads(a.compare.read_text())
        for name, now in res.items():
            was = before.get(name, {})
            differ = sorted(k for k in set(was) | set(now) if was.get(k) != now.get(k))
            print(f"{name}: {len(now)} entries, "
                  + ("bit-identical" if not differ else f"differ: {', '.join(differ)}"))
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
