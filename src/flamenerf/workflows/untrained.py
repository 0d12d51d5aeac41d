"""An untrained preset's model with a toy face mesh, and a camera facing it: the frame that
benchmarks/bench_render.py times, benchmarks/gpu_kernel_check.py renders with each set of
GPU kernels and tests/model/test_gpu_bounds.py runs under Triton's bounds checks."""

from __future__ import annotations

import numpy as np
import torch

from flamenerf.config import preset
from flamenerf.data.dataset import Intrinsics
from flamenerf.geometry import look_at
from flamenerf.model.flame_nerf import FlameNeRF


def camera(size: int, dist: float = 1.0) -> tuple[Intrinsics, np.ndarray]:
    intr = Intrinsics(size, size, 1.5 * size, 1.5 * size, size / 2, size / 2)
    c2w = look_at(np.array([0.1, 0.05, dist]), np.zeros(3), np.array([0.0, 1.0, 0.0]))
    return intr, c2w


def untrained(name: str, dev: torch.device, expr_dim: int = 8, n: int = 16) -> FlameNeRF:
    """A preset's model with random weights; where it uses a face-mesh model (the per-control
    prior of `fast`), an n x n grid 'face' facing the camera whose controls each move a
    band of it, so that the prior's cost is in the timing; where it has detail levels (also
    `fast`), a head-sized region behind that face and the finest level a trained run settles
    to on the built-in scene at 128 px (~3.7 x the grid's), so that theirs is too."""
    torch.manual_seed(0)
    faces = [(i * n + j, i * n + j + 1, (i + 1) * n + j) for i in range(n - 1)
             for j in range(n - 1)]
    cfg = preset(name).model
    region = None
    if cfg.field.kind == "hash" and cfg.field.detail_levels > 0:
        if cfg.field.detail_max_res == 0:
            cfg.field.detail_max_res = round(3.7 * cfg.field.hash_max_res)
        region = {"centre": [0.0, 0.0, -0.05], "axes": np.eye(3).tolist(),
                  "radii": [0.2, 0.22, 0.2]}
    m = FlameNeRF(cfg, num_codes=4, expr_dim=expr_dim, near=0.5, far=1.5,
                  box_min=[-0.5] * 3, box_max=[0.5] * 3, mesh_vertices=n * n,
                  mesh_faces=len(faces), detail_region=region)
    if m.expression.uses_mesh_model:
        u = torch.linspace(-0.15, 0.15, n)
        verts = torch.stack([u[None].expand(n, n), u[:, None].expand(n, n),
                             torch.full((n, n), 0.1)], -1).reshape(-1, 3)
        basis = torch.zeros(expr_dim, n * n, 3)
        for k in range(expr_dim):
            basis[k, k * n * n // expr_dim:(k + 1) * n * n // expr_dim, 1] = 0.01
        m.set_expression_model(verts, basis, torch.tensor(faces))
    m.update_to_step(1, 1)  # every c2f band on, as after training
    return m.to(dev).eval()
