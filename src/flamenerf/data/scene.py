"""Scene bounds and in-memory ray data for training and evaluation."""

from __future__ import annotations

import numpy as np
import torch

from flamenerf.data.dataset import Dataset, Frame, Intrinsics
from flamenerf.data.head_pose import canonical_vertices, head_region, head_twists
from flamenerf.data.rays import RayBatch, pixel_directions
from flamenerf.data.prior import training_mask
from flamenerf.images import resize_image
from flamenerf.meshes import surface_points
from flamenerf.geometry import project_points
from flamenerf.data.mesh_depth import mesh_depth


def scene_box(ds: Dataset, margin: float = 0.05) -> tuple[list[float], list[float]]:
    """World AABB of every capture camera's frustum between near and far (a bounded
    scene: samples never leave [near, far], so this box holds every sample)."""
    intr = ds.intrinsics
    corners = np.array([[0, 0], [intr.w, 0], [0, intr.h], [intr.w, intr.h],
                        [intr.w / 2, intr.h / 2]], np.float64)
    d_cam = np.stack([(corners[:, 0] - intr.cx) / intr.fx, -(corners[:, 1] - intr.cy) / intr.fy,
                      -np.ones(len(corners))], -1)
    pts = []
    for fr in ds.frames:
        R, o = fr.c2w[:3, :3], fr.c2w[:3, 3]
        for t in (ds.near, ds.far):
            pts.append(o + t * d_cam @ R.T)
    pts = np.concatenate(pts)
    lo, hi = pts.min(0), pts.max(0)
    pad = (hi - lo) * margin
    return (lo - pad).tolist(), (hi + pad).tolist()


def face_pixel_resolution(ds: Dataset, intr: Intrinsics) -> int:
    """Cells per side of a grid over the model's normalised box (the longest side of
    `scene_box(ds)`) that are one pixel of `intr` wide at the face: the side over a pixel's
    footprint at the median depth of the training frames' face-mesh vertices."""
    lo, hi = scene_box(ds)
    side = float((np.asarray(hi) - np.asarray(lo)).max())
    depth = float(np.median(np.concatenate([
        project_points(ds.face_vertices[fr.position].astype(np.float64), intr, fr.c2w)[1]
        for fr in ds.split("train") or ds.frames])))
    return max(1, round(side * intr.fx / depth))


def model_head_region(cfg, ds: Dataset) -> dict | None:
    """The head region a model built for `ds` with config `cfg` follows (its init argument
    `head_region`), or None: no head poses, or `model.head.follow` off."""
    if not (ds.has_head_poses and cfg.model.head.follow):
        return None
    return head_region(ds, cfg.model.head.region_scale).to_dict()


def model_warp_region(cfg, ds: Dataset) -> dict | None:
    """Where a model built for `ds` with `cfg` deforms a still head (its init argument
    `warp_region`): the head's region with `model.warp.still_head_only` on a dataset
    without head poses, else None (the warp acts everywhere, or in the followed head's
    region). A dataset with head poses trained with `model.head.follow` off keeps its warp
    everywhere: its head moves in the world, out of any fixed region, and only the
    per-frame codes move it (the `static` ablation of benchmarks/bench_head_pose.py)."""
    w = cfg.model.warp
    if not (w.enabled and w.still_head_only) or ds.has_head_poses:
        return None
    return head_region(ds, cfg.model.head.region_scale).to_dict()  # as a followed head's


def model_detail_region(cfg, ds: Dataset) -> dict | None:
    """Where a model built for `ds` with `cfg` evaluates its hash field's detail levels (its
    init argument `detail_region`): the head's region in the canonical frame, or None
    without detail levels."""
    if not (cfg.model.field.kind == "hash" and cfg.model.field.detail_levels > 0):
        return None
    return head_region(ds).to_dict()


class FrameSet:
    """Frames of a dataset held as tensors at one resolution.

    images (N, H, W, 3), masks (N, H, W) bool, c2w (N, 4, 4), frame_index (N,) long
    (frames outside the capture use code 0), expressions (N, E), face_vertices (N, V, 3)
    world; with head poses, head (N, 6): the twists of the frames' canonical-from-world
    head transforms (data/head_pose.py), else None.
    """

    def __init__(self, ds: Dataset, frames: list[Frame], intr: Intrinsics,
                 load_images: bool = True):
        self.ds, self.frames, self.intr = ds, frames, intr
        n = len(frames)
        if load_images:
            imgs = [resize_image(ds.load_image(f), intr.w, intr.h) for f in frames]
            masks = [training_mask(ds.load_mask(f), intr.w, intr.h) for f in frames]
            self.images = torch.from_numpy(np.stack(imgs)).float()
            self.masks = torch.from_numpy(np.stack(masks))
        self.c2w = torch.from_numpy(np.stack([f.c2w for f in frames])).float()
        self.frame_index = torch.tensor(
            [0 if f.frame_index is None else f.frame_index for f in frames], dtype=torch.long)
        self.expressions = torch.from_numpy(ds.expression_matrix(frames))
        self.face_vertices = torch.from_numpy(ds.face_vertices[[f.position for f in frames]])
        tw = head_twists(ds, frames)
        self.head = None if tw is None else torch.from_numpy(tw)
        self._canonical_vertices = (self.face_vertices if tw is None else
                                    torch.from_numpy(canonical_vertices(ds, frames)))
        self.faces = torch.from_numpy(ds.faces).long()
        self.dirs_cam = pixel_directions(intr)  # (H, W, 3)
        self.n = n

    def head_of(self, i: int) -> torch.Tensor | None:
        """Frame i's head twist (6,), or None without head poses."""
        return None if self.head is None else self.head[i]

    def rays(self, fi: torch.Tensor, ys: torch.Tensor, xs: torch.Tensor):
        """Rays of pixels (fi, ys, xs), each (B,) long -> origins (B, 3), dirs (B, 3)."""
        d = self.dirs_cam[ys, xs]
        R = self.c2w[fi, :3, :3]
        return self.c2w[fi, :3, 3], (R @ d[..., None])[..., 0]

    def sample_pixels(self, batch: int, generator: torch.Generator, face_fraction: float = 0.0):
        """Uniformly random pixels of random frames -> fi, ys, xs, each (batch,) long. With
        `face_fraction` > 0 that share of the batch is drawn from the face silhouettes'
        pixels instead (the face is a small part of the image but all of what β controls)."""
        k = int(round(batch * face_fraction)) if face_fraction > 0 else 0
        fi = torch.randint(self.n, (batch - k,), generator=generator)
        ys = torch.randint(self.intr.h, (batch - k,), generator=generator)
        xs = torch.randint(self.intr.w, (batch - k,), generator=generator)
        if k == 0:
            return fi, ys, xs
        if getattr(self, "_face_pixels", None) is None:
            self._face_pixels = self.masks.reshape(-1).nonzero()[:, 0]
        if len(self._face_pixels) == 0:
            return self.sample_pixels(batch, generator)
        flat = self._face_pixels[torch.randint(len(self._face_pixels), (k,), generator=generator)]
        hw = self.intr.h * self.intr.w
        return (torch.cat([fi, flat // hw]), torch.cat([ys, (flat % hw) // self.intr.w]),
                torch.cat([xs, flat % self.intr.w]))

    def ray_batch(self, fi: torch.Tensor, ys: torch.Tensor, xs: torch.Tensor,
                  deform_code: torch.Tensor, appearance_code: torch.Tensor,
                  device: torch.device | str = "cpu") -> tuple[RayBatch, torch.Tensor]:
        """The rays of pixels (fi, ys, xs) (each (B,) long) with per-ray codes ω (B, D) and
        φ (B, A), their frames' β and prior mask, and their pixels' colours.
        -> (RayBatch on `device`, target rgb (B, 3))."""
        o, d = self.rays(fi, ys, xs)
        rays = RayBatch(o.to(device), d.to(device), deform_code, appearance_code,
                        self.expressions[fi].to(device), self.masks[fi, ys, xs].to(device),
                        None if self.head is None else self.head[fi].to(device))
        return rays, self.images[fi, ys, xs].to(device)

    def mesh_depths(self) -> torch.Tensor:
        """The face mesh's z-depth through every pixel of every frame, inf off the mesh and
        on its outline (one pixel eroded: a pixel there is partly background).
        -> (N, H, W) float32, computed on first use."""
        if getattr(self, "_mesh_depths", None) is None:
            from scipy import ndimage

            dirs, faces, out = self.dirs_cam.numpy(), self.faces.numpy(), []
            for i in range(self.n):
                d = mesh_depth(self.face_vertices[i].numpy(), faces, self.intr,
                               self.c2w[i].numpy().astype(np.float64), dirs)
                d[~ndimage.binary_erosion(np.isfinite(d))] = np.inf
                out.append(d)
            self._mesh_depths = torch.from_numpy(np.stack(out))
        return self._mesh_depths

    def true_depths(self) -> np.ndarray | None:
        """Every frame's ground-truth z-depth (the built-in scene's) at this resolution, each
        pixel the nearest of the dataset's; None where a frame has none (captured clips).
        -> (N, H, W) float32."""
        out = []
        for fr in self.frames:
            d = self.ds.load_depth(fr)
            if d is None:
                return None
            t = torch.from_numpy(np.ascontiguousarray(d, np.float32))[None, None]
            out.append(torch.nn.functional.interpolate(
                t, size=(self.intr.h, self.intr.w), mode="nearest-exact")[0, 0].numpy())
        return np.stack(out)

    def face_points(self, fi: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """One uniformly random point on the face mesh of each frame in fi, in the canonical
        frame (where the deformation field sees it; the world without head poses).
        -> (B, 3)."""
        tri = torch.randint(len(self.faces), (len(fi),), generator=generator)
        uv = torch.rand(len(fi), 2, generator=generator)
        return surface_points(self._canonical_vertices, self.faces, tri, uv, which=fi)
