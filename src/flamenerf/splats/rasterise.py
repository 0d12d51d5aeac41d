"""The reference rasteriser of baked splats: what the web player draws, in PyTorch.

Each splat is drawn as WebGL draws a point sprite: a square of `size · fx / depth` pixels
(clamped to [1, MAX_POINT_PX]) centred on its projection, covering the pixels whose centres
lie inside it, with one colour. Its depth grows away from its centre, as a sphere's would
(`BULGE`: `depth + BULGE · size · r²`, r the distance from the centre over half the side),
and the nearest wins each pixel (a depth test). So splats wide enough to close the gaps
between them at a new view still leave each pixel of the view a splat was baked from to
that splat, where the surface is not steep, and the page and this function draw the same
image.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from flamenerf.data.dataset import Intrinsics

MAX_POINT_PX = 32.0
"""The largest splat drawn, in pixels (point sprites are clamped to a device's range;
every WebGL2 device draws at least this)."""

BULGE = 4.0
"""How far a splat's depth recedes at the edge of its square, in splat sides."""

NEAR = 1e-3
"""Splats closer to the camera than this (scene units) are not drawn."""


def project(points: Tensor, c2w: Tensor, intr: Intrinsics) -> tuple[Tensor, Tensor, Tensor]:
    """points (N, 3) world, c2w (4, 4) OpenGL axes -> u (N,), v (N,) pixel coordinates
    (pixel i's centre at i + 0.5) and z-depth (N,) (positive in front of the camera)."""
    R, t = c2w[:3, :3], c2w[:3, 3]
    cam = (points - t) @ R  # world -> camera: R^T (p - t), row vectors
    depth = -cam[:, 2]
    safe = depth.clamp_min(NEAR)
    u = intr.cx + intr.fx * cam[:, 0] / safe
    v = intr.cy - intr.fy * cam[:, 1] / safe
    return u, v, depth


@torch.no_grad()
def rasterise(positions: Tensor | np.ndarray, colours: Tensor | np.ndarray,
              sizes: Tensor | np.ndarray, c2w: Tensor | np.ndarray, intr: Intrinsics
              ) -> dict[str, Tensor]:
    """positions (N, 3), colours (N, 3), sizes (N,) world side lengths, c2w (4, 4) ->
    rgb (H, W, 3) (black where no splat falls), depth (H, W) z-depth of the winning splat
    (0 where none) and hit (H, W) bool."""
    pos = torch.as_tensor(np.asarray(positions), dtype=torch.float32)
    col = torch.as_tensor(np.asarray(colours), dtype=torch.float32)
    size = torch.as_tensor(np.asarray(sizes), dtype=torch.float32)
    c2w_t = torch.as_tensor(np.asarray(c2w), dtype=torch.float32)
    W, H = intr.w, intr.h
    u, v, depth = project(pos, c2w_t, intr)
    depth_of = depth
    px = (size * intr.fx / depth.clamp_min(NEAR)).clamp(1.0, MAX_POINT_PX)
    keep = (depth > NEAR) & (u + px / 2 > 0) & (u - px / 2 < W) & (v + px / 2 > 0) & (
        v - px / 2 < H)
    idx = torch.nonzero(keep).squeeze(1)
    u, v, depth, px = u[idx], v[idx], depth[idx], px[idx]
    # the pixels whose centres (i + 0.5) lie within [u - px/2, u + px/2]
    x0 = torch.ceil(u - px / 2 - 0.5).long()
    x1 = torch.floor(u + px / 2 - 0.5).long()
    y0 = torch.ceil(v - px / 2 - 0.5).long()
    y1 = torch.floor(v + px / 2 - 0.5).long()
    size = size[idx]
    # widest first, so that each offset in the square visits only the splats that reach it
    ext = torch.maximum(x1 - x0, y1 - y0) + 1
    order = torch.argsort(ext, descending=True)
    idx, u, v, depth, size, ext = idx[order], u[order], v[order], depth[order], size[order], \
        ext[order]
    x0, x1, y0, y1 = x0[order], x1[order], y0[order], y1[order]
    half = px[order] / 2
    best = torch.full((H * W,), torch.iinfo(torch.int64).max, dtype=torch.int64)
    reach = int(ext[0].item()) if len(idx) else 0
    wider = [int((ext > m).sum()) for m in range(reach)]  # splats more than m pixels a side
    for dy in range(reach):
        for dx in range(reach):
            n = wider[max(dx, dy)]
            rows, cols = y0[:n] + dy, x0[:n] + dx
            on = (rows <= y1[:n]) & (rows >= 0) & (rows < H) & (cols <= x1[:n]) & (
                cols >= 0) & (cols < W)
            if not on.any():
                continue
            r2 = (((cols[on] + 0.5 - u[:n][on]) ** 2 + (rows[on] + 0.5 - v[:n][on]) ** 2)
                  / half[:n][on] ** 2)
            d_eff = (depth[:n][on] + BULGE * size[:n][on] * r2).clamp_min(NEAR)
            # a float's bits order as the float does for positive values: depth and splat
            # index in one int64 key, so one amin picks the nearest (ties: lowest index)
            key = (d_eff.view(torch.int32).long() << 32) | idx[:n][on]
            best.scatter_reduce_(0, rows[on] * W + cols[on], key, "amin")
    hit = best != torch.iinfo(torch.int64).max
    winner = (best[hit] & 0xFFFFFFFF)
    rgb = torch.zeros(H * W, 3)
    z = torch.zeros(H * W)
    rgb[hit] = col[winner]
    z[hit] = depth_of[winner]
    return {"rgb": rgb.view(H, W, 3), "depth": z.view(H, W), "hit": hit.view(H, W)}


def render_avatar(avatar, expression: np.ndarray, c2w: np.ndarray, intr: Intrinsics
                  ) -> dict[str, Tensor]:
    """A `splats.avatar.BakedAvatar` at expression (K,) seen from c2w (4, 4): as
    `rasterise`."""
    pos, col = avatar.at(expression)
    return rasterise(pos, col, avatar.sizes, c2w, intr)
