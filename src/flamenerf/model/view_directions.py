"""The view direction a ray's colour is taken at, outside training: kept near the
capture's (data/captured_views.py says which views those are). The view direction's
encoding extrapolates beyond the captured range (pale faces, lips without their red), so a
ray far from every captured view takes its colour at the nearest one, turned towards the
direction asked by at most the allowed angle."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from flamenerf.model.se3 import apply_se3, exp_se3


def captured_direction(captured: tuple[Tensor, Tensor | None, Tensor], max_angle: float,
                       origins: Tensor, dirs: Tensor, head: Tensor | None,
                       share: Tensor | None) -> Tensor:
    """The view direction a ray's colour is taken at, kept within `max_angle` (radians)
    of the capture: of the training frames' camera centres, the one that sees the ray's
    point nearest the face (its `focus`) from the direction closest to the ray's; a
    ray further than the angle from it turns towards it until the angle is left. Rays
    from training cameras keep their direction. Everything happens in the frame the
    ray's direction is in: moved by `share` of its head twist (`FlameNeRF._head_points`), where
    frame f's centre is at exp(share ξ_f) c_f.
    Origins (R, 3), unit directions (R, 3) in that frame, twists (R, 6) and shares (R,)
    (None without head motion) -> unit directions (R, 3). `captured`: the views' camera
    centres (N, 3), their head twists (N, 6) or None, and the focus (3,)
    (`FlameNeRF.set_captured_views`)."""
    world, twists, focus = captured
    moved = share is not None and twists is not None
    if moved:
        rot, p = exp_se3(head[:, :3], head[:, 3:])
        f = torch.einsum("rji,rj->ri", rot, focus - p)  # the focus where the ray sees it
        # the ray's own direction in the world: undo its share of the head's turn
        dw = apply_se3(-share[:, None] * head[:, :3], torch.zeros_like(dirs), dirs)
    else:
        f, dw = focus.expand_as(origins), dirs
    xw = origins + ((f - origins) * dw).sum(-1, keepdim=True) * dw  # (R, 3)
    # the still world's rays (all of them without head motion) as (R, N) products
    # rather than (R, N, 3) vectors: a 256 px frame's overhead is then a few ms
    cos = ((xw * dirs).sum(-1, keepdim=True) - dirs @ world.T) / torch.sqrt(
        ((xw * xw).sum(-1, keepdim=True) - 2 * xw @ world.T + (world * world).sum(-1)
         ).clamp_min(1e-12))
    cos, k = cos.max(1)
    uk = F.normalize(xw - world[k], dim=-1)
    if moved and bool((share > 0).any()):
        r = (share > 0).nonzero()[:, 0]
        s = share[r, None]
        xs = apply_se3(s * head[r, :3], s * head[r, 3:], xw[r])
        centres = apply_se3(s[:, None] * twists[None, :, :3],
                            s[:, None] * twists[None, :, 3:],
                            world[None].expand(len(r), -1, -1))  # (r, N, 3)
        u = F.normalize(xs[:, None] - centres, dim=-1)
        cos_r, k_r = (u * dirs[r, None]).sum(-1).max(1)
        cos = cos.index_put((r,), cos_r)
        uk = uk.index_put((r,), u[torch.arange(len(r), device=r.device), k_r])
    # within `max_angle` of a captured view the direction stays as asked;
    # beyond, it turns from that view towards the one asked by that angle only (slerp)
    a = torch.acos(cos.clamp(-1.0, 1.0))[:, None]
    th = torch.full_like(a, max_angle)
    turned = (torch.sin(a - th) * uk + torch.sin(th) * dirs) / torch.sin(a).clamp_min(1e-9)
    return torch.where(a > th, F.normalize(turned, dim=-1), dirs)

