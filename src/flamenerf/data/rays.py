"""Camera rays. Directions have unit -z component in camera space, so a ray parameter t
equals z-depth (the dataset's depth convention); normalise them before encoding."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from flamenerf.data.dataset import Intrinsics


def pixel_directions(intr: Intrinsics, device: torch.device | str = "cpu") -> torch.Tensor:
    """Camera-space ray directions through pixel centres, OpenGL axes. -> (H, W, 3)."""
    ys, xs = torch.meshgrid(
        torch.arange(intr.h, dtype=torch.float32, device=device) + 0.5,
        torch.arange(intr.w, dtype=torch.float32, device=device) + 0.5,
        indexing="ij",
    )
    return torch.stack(
        [(xs - intr.cx) / intr.fx, -(ys - intr.cy) / intr.fy, -torch.ones_like(xs)], dim=-1
    )


def camera_rays(
    intr: Intrinsics, c2w: np.ndarray | torch.Tensor, device: torch.device | str = "cpu"
) -> tuple[torch.Tensor, torch.Tensor]:
    """World-space rays of every pixel. -> origins (H, W, 3), directions (H, W, 3)."""
    c2w = torch.as_tensor(np.asarray(c2w), dtype=torch.float32, device=device)
    d_cam = pixel_directions(intr, device)
    dirs = d_cam @ c2w[:3, :3].T
    origins = c2w[:3, 3].expand_as(dirs)
    return origins, dirs


@dataclass
class RayBatch:
    """R rays with everything the field is conditioned on."""

    origins: Tensor  # (R, 3) world
    dirs: Tensor  # (R, 3) world, unit -z component in camera space (t = z-depth)
    deform_code: Tensor  # (R, code_dim) ω
    appearance_code: Tensor  # (R, appearance_dim) φ
    expression: Tensor  # (R, E) β
    face_ray: Tensor  # (R,) bool: the ray passes through the face silhouette
    # (R, 6) twist log(T) of the ray's frame's canonical-from-world head transform
    # (data/head_pose.py); None: the head is the world (no head poses)
    head: Tensor | None = None

    def __getitem__(self, s) -> "RayBatch":
        return RayBatch(*(None if getattr(self, k) is None else getattr(self, k)[s]
                          for k in self.__dataclass_fields__))

    def __len__(self) -> int:
        return self.origins.shape[0]

    def to(self, device) -> "RayBatch":
        return RayBatch(*(None if getattr(self, k) is None else getattr(self, k).to(device)
                          for k in self.__dataclass_fields__))
