"""Render a re-animation: frame 0's codes (ω_0, φ_0), a sequence of expressions β_t,
cameras and (optionally) head poses, the prior's mask from the face mesh for each camera. Frames are produced one at a
time (each in chunks of rays, `render_image`), so memory does not grow with the length; from a
still camera only the face's pixels are rendered again."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch

from flamenerf.data.dataset import Dataset, Intrinsics
from flamenerf.model.flame_nerf import FlameNeRF
from flamenerf.model.inference import FAST, RenderSettings
from flamenerf.model.render_image import StillCamera
from flamenerf.data.prior import prior_mask
from flamenerf.images import colorize_depth
from flamenerf.splats.avatar import BakedAvatar
from flamenerf.splats.rasterise import render_avatar


@dataclass
class RenderedFrame:
    rgb: np.ndarray  # (H, W, 3) float32 in [0, 1]
    depth: np.ndarray  # (H, W) float32 z-depth
    acc: np.ndarray  # (H, W) float32 opacity
    mask: np.ndarray  # (H, W) bool, the prior's mask used


def render_sequence(model: FlameNeRF, ds: Dataset, intr: Intrinsics, cameras: np.ndarray,
                    expressions: np.ndarray, vertices: np.ndarray, omega: torch.Tensor,
                    phi: torch.Tensor, dilate_px: int, chunk: int | None = None,
                    heads: np.ndarray | None = None, settings: RenderSettings = FAST
                    ) -> Iterator[RenderedFrame]:
    """cameras (T, 4, 4); expressions (T, E); vertices (T, V, 3) world (posed by the
    frame's head pose), or (V, 3) for one mesh for every frame (frame 0's); ω (code_dim,)
    and φ (appearance_dim,) for every frame, or (T, code_dim) and (T, appearance_dim):
    each frame's own (`Run.clip_codes`); heads (T, 6): each frame's head twist
    (data/head_pose.py), or None for the head at frame 0's pose. The inference path by
    default: with one ω the warp's bake serves every frame (`settings.warp_grid`; give 0
    with a code per frame, which would bake each).

    A frame whose camera, head pose and codes are the previous frame's (a still camera:
    `render`'s default for a drive or keyframes) renders only the pixels inside the prior's
    silhouette of either frame and keeps the others, which β does not reach
    (`expression_confined`)."""
    T = len(cameras)
    per_frame = omega.dim() == 2
    still = None  # the renderer of the current camera, head pose and codes
    for i in range(T):
        verts = vertices[i] if vertices.ndim == 3 else vertices
        mask = prior_mask(ds, verts, cameras[i], intr, dilate_px)
        beta = torch.as_tensor(np.asarray(expressions[i], np.float32))
        head = None if heads is None else torch.as_tensor(np.asarray(heads[i], np.float32))
        w, a = (omega[i], phi[i]) if per_frame else (omega, phi)
        if (still is None or not still.same_view(intr, cameras[i], head)
                or not still.same_codes(w, a)):
            still = StillCamera(model, intr, np.asarray(cameras[i]).copy(), w, a, head,
                                chunk, settings)
        out = still(beta, mask)
        yield RenderedFrame(out["rgb"].numpy(), out["depth"].numpy(), out["acc"].numpy(), mask)


def baked_sequence(avatar: BakedAvatar, ds: Dataset, intr: Intrinsics, cameras: np.ndarray,
                   expressions: np.ndarray, vertices: np.ndarray, dilate_px: int
                   ) -> Iterator[RenderedFrame]:
    """`render_sequence` of a bake (splats/avatar.py): frame 0's codes and head pose, as
    baked; acc is 1 where a splat falls. The prior's mask is computed as for the run (the
    side by side shows it), though the bake needs none: its offsets are the face's."""
    for i in range(len(cameras)):
        verts = vertices[i] if vertices.ndim == 3 else vertices
        mask = prior_mask(ds, verts, cameras[i], intr, dilate_px)
        out = render_avatar(avatar, np.asarray(expressions[i], np.float32), cameras[i], intr)
        yield RenderedFrame(out["rgb"].numpy(), out["depth"].numpy(),
                            out["hit"].numpy().astype(np.float32), mask)


def depth_range(frame: RenderedFrame, near: float, far: float) -> tuple[float, float]:
    """A fixed colour-map range for a depth video: 1st-99th percentile of the first frame's
    opaque pixels (near..far if none)."""
    d = frame.depth[frame.acc > 0.5]
    if d.size < 10:
        return near, far
    lo, hi = np.percentile(d, [1, 99])
    return float(lo), float(max(hi, lo + 1e-3))


def depth_image(frame: RenderedFrame, lo: float, hi: float) -> np.ndarray:
    """Colour-mapped depth, faded to black where the ray hit nothing."""
    return colorize_depth(frame.depth, lo, hi) * np.clip(frame.acc, 0, 1)[..., None]
