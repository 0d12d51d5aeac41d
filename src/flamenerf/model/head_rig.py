"""The head's rig: a clip where the head turns on its own (datasets with head poses) is
learnt with the head in one canonical pose. Points inside the head's ellipsoid take the
frame's head motion, points outside stay with the still world, and a band around it (the
neck, the hair) blends between them; a still head's deformation can be kept to the same
ellipsoid (`warp.still_head_only`)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from flamenerf.geometry import ellipsoid_weight
from flamenerf.model.se3 import apply_se3, exp_se3


class HeadRig(nn.Module):
    """The ellipsoid `region` (data/head_pose.HeadRegion.to_dict, world units) and the
    blend `band` (a fraction of its radius) of points that follow the head."""

    def __init__(self, region: dict, band: float):
        super().__init__()
        self.band = float(band)
        for k in ("centre", "axes", "radii"):  # the region's, for the device only
            self.register_buffer(k, torch.tensor(region[k]).float(), persistent=False)

    def weight(self, x: Tensor, band: float | None = None) -> Tensor:
        """How much of the head's motion canonical points x (*bs, 3) (world units) take:
        1 inside the head's ellipsoid, a smoothstep down to 0 at 1 + band times its radius
        (the neck and hair blend into the static world; band: the rig's unless given).
        -> (*bs,)"""
        return ellipsoid_weight(x, self.centre, self.axes, self.radii,
                                self.band if band is None else band)

    def points(self, x: Tensor, dirs: Tensor, head: Tensor
               ) -> tuple[Tensor, Tensor, Tensor]:
        """World samples x (R, S, 3) and ray directions (R, 3) of rays with head twists
        ξ (R, 6) -> canonical samples (R, S, 3), directions (R, 3), and the share of the
        head's motion each ray's direction took (R,): a sample moves by exp(w ξ) with w =
        `weight` of where the full motion exp(ξ) takes it, so the head follows its pose and
        the background stays put. A ray's direction turns with the most head-bound of its
        samples (the view direction of what it sees when it meets the head; per ray, so
        that a still head leaves every tensor as without one)."""
        rot, p = exp_se3(head[:, :3], head[:, 3:])  # the full motion, one matrix per ray
        full = torch.baddbmm(p[:, None], x, rot.transpose(1, 2))  # (R, S, 3)
        w = self.weight(full)  # (R, S)
        # inside the head (w = 1) and the still world (w = 0) need no per-point screw, and a
        # render's samples are mostly one or the other: half the time of the per-point
        # screw everywhere (4096 rays x 48 samples, one thread; a 128 px frame of the
        # expressions clip 0.36 -> 0.31 s, 256 px unchanged)
        xc = torch.where((w >= 1)[..., None], full, x)
        band = (w > 0) & (w < 1)
        if bool(band.any()):
            rows, wb = band.nonzero()[:, 0], w[band][:, None]
            xc[band] = apply_se3(wb * head[rows, :3], wb * head[rows, 3:], x[band])
        share = w.amax(1)
        dc = apply_se3(share[:, None] * head[:, :3], torch.zeros_like(dirs), dirs)
        return xc, dc, share
