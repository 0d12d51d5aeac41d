"""Bake a trained run into splats with per-control linear offsets (splats/avatar.py).

Supervision is the run itself: from a set of views (frame 0's camera, then the capture's
cameras and the render's orbit and spiral paths, spread by farthest-point sampling), the run
renders frame 0's codes at the reference expression, and each control moved alone to the
far end of its training range. Every pixel of a view that the splats baked so far do not
already show (a hole, or another colour at the same depth) becomes a splat at the rendered
z-depth with the rendered colour, a square three pixels wide at that depth. For
the pixels inside the spatial prior's silhouette of any of those expressions (the only
rays β reaches in the run), and only where the splat lies near the face mesh, the change
of colour and of depth per unit of each control becomes the splat's offset: nothing else
carries one, so nothing outside the face moves with β in the bake, by construction.

Offsets are the secant from the reference to the end of the range, so an expression in
between is the linear blend of the two renders (Gaussian-blendshape-like); what the run
does non-linearly in between (a blink's half-closed lid) is approximated.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
import torch
import tyro
from tqdm import tqdm

from flamenerf.data.dataset import Dataset, Intrinsics, reference_position
from flamenerf.data.expression_range import training_range
from flamenerf.data.prior import dataset_dilation, mesh_function, prior_mask
from flamenerf.data.rays import camera_rays
from flamenerf.errors import UserError
from flamenerf.model.inference import FAST
from flamenerf.model.render_image import StillCamera
from flamenerf.rendering import cameras as C
from flamenerf.rendering.videos import render_intrinsics
from flamenerf.splats.avatar import BakedAvatar, save_avatar
from flamenerf.splats.rasterise import rasterise
from flamenerf.training.run import Run, load_run

SPLAT_PX = 3.0
"""A splat's side in pixels at the depth and view it was baked from: wide enough that
neighbours still overlap from other views (the rasteriser's bulge leaves each pixel of
the view to its own splat)."""

WIDE_ORBIT = 1.5
"""The widest orbit baked from, in the capture's azimuth half-ranges."""

MIN_SPAN = 0.02
"""Controls whose training range is narrower than this carry no offsets (nothing learnt)."""

DEPTH_TOLERANCE = 0.03
"""A view's pixel is already shown by the splats when their depth there is within this share
of the rendered depth and their colour within `COLOUR_TOLERANCE` (mean over channels)."""
COLOUR_TOLERANCE = 0.06

FACE_BOX_MARGIN = 0.3
"""Splats carry offsets only within the face meshes' bounding box grown by this share of
its largest side on every side (the meshes of every expression baked)."""


@dataclass
class BakeOptions:
    run: Annotated[Path, tyro.conf.Positional]
    """Trained run directory."""
    out: Path | None = None
    """Where to write the bake (default RUN/baked.npz)."""
    views: int = 24
    """Views baked from (frame 0's camera first)."""
    size: int | None = None
    """Bake at this many pixels wide (default: the run's training resolution)."""
    dataset: Path | None = None
    """The run's dataset, if it moved."""
    device: str = "auto"


@dataclass
class BakeSummary:
    path: Path
    splats: int
    face_splats: int
    controls: int
    views: int
    seconds: float
    per_view: list[int] = field(default_factory=list)

    def describe(self) -> str:
        return (f"baked {self.splats} splats ({self.face_splats} on the face, {self.controls} "
                f"controls with offsets) from {self.views} views in {self.seconds:.0f} s: "
                f"{self.path}")


def bake_views(ds: Dataset, count: int) -> np.ndarray:
    """`count` camera-to-world matrices (count, 4, 4): frame 0's first, then, spread by
    farthest-point sampling of the eyes, half among the capture's training cameras and the
    rest among the render's orbit and spiral paths and a wider orbit (what users look
    from). The capture's come first: where the run saw the scene its renders are right,
    and later views only add what earlier ones left out (`bake_run`)."""
    rig = C.rig_from_dataset(ds)
    train = np.stack([f.c2w for f in ds.split("train")]).astype(np.float64)
    paths = np.concatenate([C.camera_path("orbit", 32, rig), C.camera_path("spiral", 32, rig),
                            C.camera_path("orbit", 32, rig, WIDE_ORBIT * rig.swing_deg)])
    chosen = [np.asarray(rig.reference, np.float64)]
    for pool, n in ((train, (count + 1) // 2), (paths, count)):
        eyes = pool[:, :3, 3]
        dist = np.min([np.linalg.norm(eyes - c[:3, 3], axis=1) for c in chosen], 0)
        while len(chosen) < min(n, count):
            nxt = int(dist.argmax())
            if dist[nxt] <= 1e-6:  # every camera left stands where one chosen does
                break
            chosen.append(pool[nxt])
            dist = np.minimum(dist, np.linalg.norm(eyes - eyes[nxt], axis=1))
    return np.stack(chosen)


EDGE = 0.05
"""A pixel lies on a depth edge when the depths of its 3×3 neighbourhood span more than this
share of its own."""


def snapped_depth(depth: torch.Tensor) -> torch.Tensor:
    """depth (H, W) z-depth -> the same, with each pixel on a depth edge moved to the nearer
    of its neighbourhood's nearest and farthest depths: a ray that grazes the hair and then
    meets the wall renders a depth between the two, a splat there would float in mid-air
    at every other view."""
    d = depth[None, None]
    hi = torch.nn.functional.max_pool2d(d, 3, 1, 1, ceil_mode=False)
    lo = -torch.nn.functional.max_pool2d(-d, 3, 1, 1)
    hi, lo = hi[0, 0], lo[0, 0]
    edge = (hi - lo) > EDGE * depth.clamp_min(1e-6)
    near = (depth - lo).abs() <= (hi - depth).abs()
    return torch.where(edge, torch.where(near, lo, hi), depth)


def _targets(lo: np.ndarray, hi: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Each control's far end of its range from the reference (K,); NaN: none to bake."""
    up, down = hi - ref, ref - lo
    t = np.where(up >= down, hi, lo).astype(np.float32)
    t[(hi - lo) < MIN_SPAN] = np.nan
    t[np.abs(t - ref) < MIN_SPAN / 2] = np.nan
    return t


def bake_run(run: Run, ds: Dataset, intr: Intrinsics, views: np.ndarray,
             progress: bool = True) -> tuple[BakedAvatar, list[int]]:
    """The avatar baked from `views` (V, 4, 4) at `intr`, and the splats each view added."""
    model = run.model
    names = run.expression_names
    ref_pos = reference_position(ds)
    ref = ds.frames[ref_pos].expression.astype(np.float32)
    rng = training_range(ds, model.generic_controls)
    lo, hi = np.asarray(rng.lo, np.float32), np.asarray(rng.hi, np.float32)
    targets = _targets(lo, hi, ref)
    moved = [k for k in range(len(names)) if np.isfinite(targets[k])]
    mesh_of = mesh_function(model, ds)
    dil = dataset_dilation(ds)
    exprs = [ref]
    for k in moved:
        b = ref.copy()
        b[k] = targets[k]
        exprs.append(b)
    # frame 0's own mesh is its canonical one: the head at frame 0's pose, as render poses it
    meshes = [mesh_of(b) for b in exprs]
    allv = np.concatenate(meshes)
    box_lo, box_hi = allv.min(0), allv.max(0)
    grow = (box_hi - box_lo).max() * FACE_BOX_MARGIN  # a flat mesh still has depth
    box_lo, box_hi = box_lo - grow, box_hi + grow

    omega, phi = run.frame_codes(0)
    pos, col, size, face_rows, dpos, dcol = [], [], [], [], [], []
    n_total = 0
    added = []
    for c2w in tqdm(views, desc="bake", unit="view", disable=not progress):
        still = StillCamera(model, intr, c2w.copy(), omega, phi, None, None, FAST)
        masks = [prior_mask(ds, m, c2w, intr, dil) for m in meshes]
        base = still(torch.as_tensor(ref), masks[0])
        rgb0, z0 = base["rgb"].reshape(-1, 3), snapped_depth(base["depth"]).reshape(-1)
        if n_total:
            seen = rasterise(torch.cat(pos), torch.cat(col), torch.cat(size), c2w, intr)
            # what the splats leave out, or show at the right depth in another colour; not
            # where they stand at another depth: a render off the capture puts the run's
            # floaters there, which would then hide the scene from every other view
            same_depth = (seen["depth"].reshape(-1) - z0).abs() <= DEPTH_TOLERANCE * z0
            recoloured = (seen["rgb"].reshape(-1, 3) - rgb0).abs().mean(1) > COLOUR_TOLERANCE
            new = ~seen["hit"].reshape(-1) | (same_depth & recoloured)
        else:
            new = torch.ones(intr.w * intr.h, dtype=torch.bool)
        new &= z0 > 0
        o, d = camera_rays(intr, c2w)
        o, d = o.reshape(-1, 3), d.reshape(-1, 3)
        p = o + d * z0[:, None]
        face = torch.as_tensor(np.any(masks, 0).reshape(-1)) & (
            (p >= torch.as_tensor(box_lo)) & (p <= torch.as_tensor(box_hi))).all(1)
        sel = torch.nonzero(new).squeeze(1)
        fsel = torch.nonzero(new & face).squeeze(1)
        pos.append(p[sel])
        col.append(rgb0[sel])
        size.append(SPLAT_PX * z0[sel] / intr.fx)
        # the face splats' rows among all splats so far
        rows = n_total + torch.searchsorted(sel, fsel)
        face_rows.append(rows)
        view_dpos = torch.zeros(len(names), len(fsel), 3)
        view_dcol = torch.zeros(len(names), len(fsel), 3)
        for j, k in enumerate(moved):
            out = still(torch.as_tensor(exprs[j + 1]), masks[j + 1])
            step = float(targets[k] - ref[k])
            view_dcol[k] = (out["rgb"].reshape(-1, 3)[fsel] - rgb0[fsel]) / step
            view_dpos[k] = d[fsel] * ((out["depth"].reshape(-1)[fsel] - z0[fsel]) / step
                                      )[:, None]
        dpos.append(view_dpos)
        dcol.append(view_dcol)
        n_total += len(sel)
        added.append(int(len(sel)))
    # the web player reads colours as bytes and offsets as half floats: quantised here, so
    # that the reference rasteriser and the page draw the same numbers
    colours = torch.round(torch.cat(col).clamp(0, 1) * 255) / 255
    avatar = BakedAvatar(
        positions=torch.cat(pos).numpy().astype(np.float32),
        colours=colours.numpy().astype(np.float32),
        sizes=torch.cat(size).numpy().astype(np.float32),
        face_index=torch.cat(face_rows).numpy().astype(np.int64),
        d_positions=torch.cat(dpos, 1).half().float().numpy(),
        d_colours=torch.cat(dcol, 1).half().float().numpy(),
        names=list(names), reference=ref, low=lo, high=hi,
        meta=_meta(run, ds, intr, views))
    return avatar, added


def _meta(run: Run, ds: Dataset, intr: Intrinsics, views: np.ndarray) -> dict:
    """What a player needs besides the splats: frame 0's camera and intrinsics (its first
    view), the head's centre and the scene's up (its orbit), the run it came from."""
    rig = C.rig_from_dataset(ds)
    return {"run": str(run.run_dir), "step": int(run.step),
            "intrinsics": {"w": intr.w, "h": intr.h, "fx": intr.fx, "fy": intr.fy,
                           "cx": intr.cx, "cy": intr.cy},
            "camera": np.asarray(rig.reference, float).tolist(),
            "center": np.asarray(rig.center, float).tolist(),
            "up": np.asarray(rig.up, float).tolist(),
            "near": float(run.model.near), "far": float(run.model.far),
            "views": int(len(views))}


def bake(opts: BakeOptions, log=print) -> BakeSummary:
    """The whole of `flamenerf bake` (see its --help)."""
    if opts.views < 1:
        raise UserError(f"--views {opts.views}: must be at least 1")
    out = Path(opts.out) if opts.out is not None else Path(opts.run) / "baked.npz"
    if out.suffix != ".npz":
        raise UserError(f"{out}: a bake is written as .npz")
    t0 = time.perf_counter()
    run = load_run(opts.run, opts.device)
    if run.model.follows_head:
        log("note: the bake shows the head at frame 0's pose (--head-pose is not baked)")
    ds = run.dataset(opts.dataset)
    intr = render_intrinsics(run, ds, opts.size)
    views = bake_views(ds, opts.views)
    avatar, added = bake_run(run, ds, intr, views)
    save_avatar(avatar, out)
    k = int((np.any(avatar.d_positions != 0, axis=(1, 2))
             | np.any(avatar.d_colours != 0, axis=(1, 2))).sum())
    return BakeSummary(out, avatar.n, len(avatar.face_index), k, len(views),
                       time.perf_counter() - t0, added)
