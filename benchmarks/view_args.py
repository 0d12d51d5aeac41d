"""The arguments of `render_image` for one view of a trained run, as the benchmarks render
it (profile_render.py, gpu_kernels_build.py, gpu_choices.py): frame 0's camera, codes and β;
or, `expressive`, the camera and β of the frame with the most expressive β (so that the
expression's kernels run) with frame 0's codes; the prior's mask at `size` px."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from flamenerf.data.prior import dataset_dilation, mesh_function, prior_mask


def view_options(ap: argparse.ArgumentParser, size: int, device: str | None = "cpu") -> None:
    """The options that choose the view: --run, --dataset, --size, and --device unless
    `device` is None (a CPU-only script)."""
    ap.add_argument("--run", type=Path, required=True)
    ap.add_argument("--dataset", type=Path, default=None, help="the run's dataset, if moved")
    if device is not None:
        ap.add_argument("--device", default=device)
    ap.add_argument("--size", type=int, default=size)


def view_args(run, ds, size: int, expressive: bool = False) -> tuple:
    """-> (model, intrinsics, c2w, ω, φ, β, mask), in render_image's order."""
    if expressive:
        fr = max(ds.frames, key=lambda f: float(np.abs(f.expression).sum()))
    else:
        fr = next(f for f in ds.frames if f.frame_index == 0)
    omega, phi = run.frame_codes(0)
    beta = np.asarray(fr.expression, np.float32)
    intr = ds.intrinsics.scaled(size / ds.intrinsics.w)
    mask = prior_mask(ds, mesh_function(run.model, ds)(beta), fr.c2w, intr,
                      dataset_dilation(ds))
    return run.model, intr, fr.c2w, omega, phi, torch.as_tensor(beta), mask
