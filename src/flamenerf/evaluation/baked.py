"""How closely a bake (splats/avatar.py) draws what its run renders: a split's frames with
frame 0's codes, their own cameras and expressions, drawn by the bake and by the run's
NeRF (the reference renderer, what eval measures), each against the other and, where the
dataset has it, against ground truth."""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from flamenerf.data.scene import FrameSet
from flamenerf.evaluation.metrics import image_metrics, summarize
from flamenerf.evaluation.protocol import render_frames
from flamenerf.splats.avatar import BakedAvatar
from flamenerf.splats.rasterise import render_avatar


def baked_frames(avatar: BakedAvatar, fs: FrameSet) -> tuple[list[np.ndarray], float]:
    """The bake drawn at every frame of `fs` -> images (H, W, 3) and seconds per frame."""
    out = []
    t0 = time.perf_counter()
    for i in range(fs.n):
        out.append(render_avatar(avatar, fs.expressions[i].numpy(), fs.c2w[i].numpy(),
                                 fs.intr)["rgb"].numpy())
    return out, (time.perf_counter() - t0) / max(fs.n, 1)


def bake_fidelity(run, avatar: BakedAvatar, fs: FrameSet, truth: bool,
                  nerf: list[np.ndarray] | None = None) -> dict[str, Any]:
    """The bake against the run's renders of `fs` (frame 0's codes) and, with `truth`,
    both against the frames' images: {"baked_vs_nerf", "baked_vs_truth",
    "nerf_vs_truth": summaries of `image_metrics`, "baked_seconds_per_frame",
    "nerf_seconds_per_frame"}. `nerf`: the run's renders, if already made."""
    omega, phi = run.frame_codes(0)
    t0 = time.perf_counter()
    if nerf is None:
        nerf = render_frames(run.model, fs, omega.expand(fs.n, -1), phi.expand(fs.n, -1))
    nerf_s = (time.perf_counter() - t0) / max(fs.n, 1)
    baked, baked_s = baked_frames(avatar, fs)
    face = fs.masks.numpy()
    res: dict[str, Any] = {
        "frames": fs.n,
        "baked_vs_nerf": summarize([image_metrics(b, n, f)
                                    for b, n, f in zip(baked, nerf, face)]),
        "baked_seconds_per_frame": baked_s, "nerf_seconds_per_frame": nerf_s}
    if truth:
        gt = fs.images.numpy()
        res["baked_vs_truth"] = summarize([image_metrics(b, g, f)
                                           for b, g, f in zip(baked, gt, face)])
        res["nerf_vs_truth"] = summarize([image_metrics(n, g, f)
                                          for n, g, f in zip(nerf, gt, face)])
    return res
