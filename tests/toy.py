"""Test fixture data: a toy dataset and toy runs, small enough for tests (well under a
second to make): a textured quad 'face' in front of a striped backdrop, seen by a few
cameras, with every split of the built-in scene (train, val, reanimate, leakage).

Imported by the tests as `toy` (tests/ is on sys.path through tests/conftest.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flamenerf.config import Config, ExpressionMode, preset
from flamenerf.data.dataset import Intrinsics
from flamenerf.data.dataset_writer import DatasetWriter
from flamenerf.geometry import look_at
from flamenerf.data.prior import rasterize_silhouette

TOY_NAMES = ["jawOpen", "mouthSmileLeft", "browInnerUp"]


def _image(intr: Intrinsics, mask: np.ndarray, expr: np.ndarray, k: int) -> np.ndarray:
    ys, xs = np.mgrid[0:intr.h, 0:intr.w] / max(intr.w, intr.h)
    bg = np.stack([0.5 + 0.4 * np.sin(8 * xs + 0.3 * k), 0.4 + 0.3 * np.cos(6 * ys),
                   0.3 + 0.2 * xs], -1)
    face = np.stack([0.8 + 0.2 * expr[0] + 0 * xs, 0.6 - 0.3 * expr[1] + 0.1 * ys,
                     0.5 + 0.3 * expr[2] + 0 * xs], -1)
    return np.where(mask[..., None], face, bg).clip(0, 1).astype(np.float32)


def make_toy_dataset(out: str | Path, size: int = 16, overwrite: bool = True) -> Path:
    """Write the toy dataset to `out` (4 train, 2 val, 2 reanimate, 3 leakage frames)."""
    intr = Intrinsics(size, size, 1.3 * size, 1.3 * size, size / 2, size / 2)
    s = 0.18
    verts = np.array([[-s, -s, 0], [s, -s, 0], [s, s, 0], [-s, s, 0]], np.float32)
    faces = np.array([[0, 1, 2], [0, 2, 3]], np.int32)
    up = np.array([0.0, 1.0, 0.0])

    def cam(yaw_deg: float, dist: float = 1.0) -> np.ndarray:
        y = np.radians(yaw_deg)
        return look_at(np.array([dist * np.sin(y), 0.05, dist * np.cos(y)]), np.zeros(3), up)

    E = len(TOY_NAMES)
    rng = np.random.default_rng(0)
    specs = [("train", i, cam(-12 + 8 * i), rng.uniform(0, 1, E)) for i in range(4)]
    specs += [("val", 4 + i, cam(-6 + 12 * i), rng.uniform(0, 1, E)) for i in range(2)]
    specs += [("reanimate", None, cam(15 * (2 * i - 1), 1.1), rng.uniform(0, 1, E))
              for i in range(2)]
    sweep = [("neutral", 0.0, np.zeros(E)), ("jawOpen", 1.0, np.eye(E)[0]),
             ("mouthSmileLeft", 1.0, np.eye(E)[1])]
    with DatasetWriter(out, intr, 0.5, 1.6, TOY_NAMES, "synthetic",
                       source={"name": "flamenerf toy"}, overwrite=overwrite,
                       prior_dilation_px=1) as w:
        for k, (split, fi, c2w, e) in enumerate(specs):
            m = rasterize_silhouette(verts, faces, intr, c2w, 1)
            w.add_frame(_image(intr, m, e, k), m, c2w, e, fi, split, verts=verts)
        for ctl, val, e in sweep:
            m = rasterize_silhouette(verts, faces, intr, specs[0][2], 1)
            w.add_frame(_image(intr, m, e, 0), m, specs[0][2], e, None, "leakage", verts=verts,
                        extra={"leakage_control": ctl, "leakage_value": val})
        w.set_faces(faces)
    return Path(out)


def toy_config(mode: ExpressionMode = "masked", steps: int = 2) -> Config:
    """The `fast` preset's machinery, shrunk: a tiny warp, hash grid and sampler."""
    cfg = preset("fast")
    cfg.model.expression_mode = mode
    w = cfg.model.warp
    w.code_dim, w.width, w.depth, w.skips, w.num_freqs, w.init_scale = 4, 16, 2, (), 4, 0.1
    f = cfg.model.field
    f.hash_levels, f.hash_log2_size, f.hash_base_res, f.hash_max_res = 4, 10, 4, 64
    f.head_width, f.geo_features, f.appearance_dim = 16, 7, 4
    s = cfg.model.sampler
    s.num_proposal, s.num_main, s.proposal_levels, s.proposal_log2_size = 16, 8, 3, 10
    s.proposal_max_res, s.proposal_width = 64, 8
    s.num_coarse, s.num_fine = 8, 8
    t = cfg.train
    t.steps, t.batch_rays, t.face_reg_points = steps, 64, 16
    t.image_every, t.checkpoint_every, t.log_every = 0, 10_000, 10_000
    # two steps leave β's effect to the initial weights: over a random colour the first
    # steps' gradients differ, and the rendering tests need a β that shows
    t.random_background = False
    # float32: whether a run trains in bfloat16 is measured when it starts, and tests
    # compare runs bit for bit
    t.bf16 = False
    return cfg


def make_toy_run(dataset: str | Path, out: str | Path, mode: ExpressionMode = "masked",
                 steps: int = 2) -> Path:
    """Train a toy run for `steps` steps on CPU (a real run directory)."""
    from flamenerf.training.trainer import train

    train(dataset, out, toy_config(mode, steps), device="cpu", quiet=True)
    return Path(out)
