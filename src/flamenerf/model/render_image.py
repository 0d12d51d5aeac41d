"""Render whole images in memory-bounded chunks of rays: the one entry point of eval,
render, the viewer and training previews. `settings` picks the path: the training forward
(REFERENCE, the default, what eval measures) or the inference path (`RenderSettings()`,
model/inference.py). On a CPU the inference path renders the chunks side by side in Python
threads with one torch thread each (`RenderSettings.threads`, runtime.map_single_threaded)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from flamenerf.data.dataset import Intrinsics
from flamenerf.data.rays import camera_rays
from flamenerf.model.flame_nerf import FlameNeRF, RayBatch
from flamenerf.model.inference import REFERENCE, RenderSettings, prepare, render_rays
from flamenerf.runtime import map_single_threaded


@torch.no_grad()
def render_image(model: FlameNeRF, intr: Intrinsics, c2w: np.ndarray | torch.Tensor,
                 deform_code: torch.Tensor, appearance_code: torch.Tensor,
                 expression: torch.Tensor, face_mask: np.ndarray | torch.Tensor,
                 chunk: int | None = None, head: torch.Tensor | None = None,
                 settings: RenderSettings = REFERENCE
                 ) -> dict[str, torch.Tensor]:
    """One camera, one set of codes -> rgb (H, W, 3), depth (H, W), acc (H, W) on CPU.

    deform_code (D,), appearance_code (A,), expression (E,), face_mask (H, W) bool: the
    spatial prior's silhouette for this camera and expression; head (6,): the twist of the
    frame's canonical-from-world head transform (data/head_pose.py), or None. `chunk` (rays
    per forward pass) overrides the settings' chunk.
    """
    out = render_pixels(model, intr, c2w, deform_code, appearance_code, expression,
                        face_mask, None, chunk, head, settings)
    return {"rgb": out["rgb"].view(intr.h, intr.w, 3).clamp(0, 1),
            "depth": out["depth"].view(intr.h, intr.w),
            "acc": out["acc"].view(intr.h, intr.w)}


@torch.no_grad()
def render_pixels(model: FlameNeRF, intr: Intrinsics, c2w: np.ndarray | torch.Tensor,
                  deform_code: torch.Tensor, appearance_code: torch.Tensor,
                  expression: torch.Tensor, face_mask: np.ndarray | torch.Tensor,
                  pixels: np.ndarray | torch.Tensor | None, chunk: int | None = None,
                  head: torch.Tensor | None = None, settings: RenderSettings = REFERENCE
                  ) -> dict[str, torch.Tensor]:
    """`render_image`'s rays of some pixels only: pixels (n,) flat indices into the
    (H, W) image (None: all) -> rgb (n, 3) (not clamped), depth (n,), acc (n,) on CPU. Each
    ray is rendered as in the whole image (the viewer re-renders only the face's pixels
    when a slider alone moves: viewer/renderer.py)."""
    dev = next(model.parameters()).device
    chunk = chunk or settings.rays_per_chunk(dev, model)
    origins, dirs = camera_rays(intr, c2w, dev)
    o, d = origins.reshape(-1, 3), dirs.reshape(-1, 3)
    mask = torch.as_tensor(np.asarray(face_mask), device=dev).reshape(-1).bool()
    if pixels is not None:
        sel = torch.as_tensor(np.asarray(pixels), dtype=torch.long, device=dev)
        o, d, mask = o[sel], d[sel], mask[sel]
    n = o.shape[0]

    def chunk_out(s: int) -> dict[str, torch.Tensor]:
        m = min(chunk, n - s)
        rays = RayBatch(o[s:s + m], d[s:s + m], deform_code.to(dev).expand(m, -1),
                        appearance_code.to(dev).expand(m, -1), expression.to(dev).expand(m, -1),
                        mask[s:s + m], None if head is None else head.to(dev).expand(m, -1))
        out = render_rays(model, rays, settings) if settings.fast else model(rays)
        if dev.type == "cpu":
            return {k: out[k] for k in ("rgb", "depth", "acc")}
        # one copy to the host (each waits for the device)
        host = torch.cat([out["rgb"], out["depth"][:, None], out["acc"][:, None]], 1).cpu()
        return {"rgb": host[:, :3], "depth": host[:, 3], "acc": host[:, 4]}

    if n == 0:
        return {"rgb": torch.zeros(0, 3), "depth": torch.zeros(0), "acc": torch.zeros(0)}
    threads = settings.render_threads(dev)
    if threads > 1:  # pieces enough for every thread to stay busy to the end
        chunk = min(chunk, max(512, -(-n // (2 * threads))))
        prepare(model, deform_code.to(dev), settings)
    outs = map_single_threaded(chunk_out, list(range(0, n, chunk)), threads)
    return {k: torch.cat([part[k] for part in outs]) for k in ("rgb", "depth", "acc")}


class StillCamera:
    """One camera and one set of codes under a changing expression: after the first image,
    only the pixels inside the prior's silhouette of the new or the last expression are
    rendered again, the others kept (β reaches no other ray where the model confines it,
    `ExpressionConditioner.confined`; otherwise every image is rendered whole). What a
    re-animation from a still camera, eval's sweeps and drives and the viewer's sliders
    render: the same pixels, ~3x faster per frame on a CPU where the face is a small part
    of the view, ~10 % where it fills a third of it (docs/results.md)."""

    def __init__(self, model: FlameNeRF, intr: Intrinsics, c2w: np.ndarray | torch.Tensor,
                 deform_code: torch.Tensor, appearance_code: torch.Tensor,
                 head: torch.Tensor | None = None, chunk: int | None = None,
                 settings: RenderSettings = REFERENCE):
        self.args = (model, intr, c2w, deform_code, appearance_code)
        self.head, self.chunk, self.settings = head, chunk, settings
        # the last image: its expression, mask and outputs (H·W rows)
        self.last: tuple[torch.Tensor, np.ndarray, dict[str, torch.Tensor]] | None = None
        self.rays = 0  # rays rendered by the last call

    def same_view(self, intr: Intrinsics, c2w: np.ndarray | torch.Tensor,
                  head: torch.Tensor | None) -> bool:
        """Whether a frame with these intrinsics, camera and head twist sees what this one
        does (then only the expression may differ)."""
        _, intr0, c2w0 = self.args[:3]
        if intr0 != intr or not np.array_equal(np.asarray(c2w0), np.asarray(c2w)):
            return False
        if self.head is None or head is None:
            return self.head is None and head is None
        return torch.equal(self.head, head)

    def same_codes(self, deform_code: torch.Tensor, appearance_code: torch.Tensor) -> bool:
        """Whether these codes are this renderer's."""
        return (torch.equal(self.args[3], deform_code)
                and torch.equal(self.args[4], appearance_code))

    def pixels(self, expression: torch.Tensor, face_mask: np.ndarray) -> np.ndarray | None:
        """The flat pixels the next image must render; None: all of them."""
        prior = self.args[0].expression  # what β reaches is the conditioner's to say
        if self.last is None or not prior.confined:
            return None
        last_expr, last_mask, _ = self.last
        if prior.reaches_nothing or (
                torch.equal(last_expr, expression) and np.array_equal(last_mask, face_mask)):
            return np.zeros(0, np.int64)  # nothing β reaches changed (the Nerfies variant:
            # β reaches nothing); the same β under another mesh's silhouette (another frame
            # of the clip) changes which rays get it
        return np.flatnonzero(np.asarray(face_mask, bool) | last_mask)

    def __call__(self, expression: torch.Tensor, face_mask: np.ndarray, band: int = 0,
                 check: Callable[[], None] | None = None) -> dict[str, torch.Tensor]:
        """expression (E,), face_mask (H, W) bool -> as `render_image`. `band`: rays per
        call of the renderer (0: all at once), with `check()` before each (the viewer's,
        which raises to abandon a stale image)."""
        intr = self.args[1]
        expression = torch.as_tensor(expression).float()
        mask = np.asarray(face_mask, bool)
        pixels = self.pixels(expression, mask)
        if pixels is None:
            n = intr.h * intr.w
            out = {"rgb": torch.zeros(n, 3), "depth": torch.zeros(n), "acc": torch.zeros(n)}
            pixels = np.arange(n)
        else:
            out = {k: v.clone() for k, v in self.last[2].items()}
        step = band if band > 0 else max(len(pixels), 1)
        for s in range(0, len(pixels), step):
            if check is not None:
                check()
            part_px = pixels[s:s + step]
            part = render_pixels(*self.args, expression, mask, part_px, self.chunk, self.head,
                                 self.settings)
            idx = torch.from_numpy(part_px)
            out["rgb"][idx] = part["rgb"].clamp(0, 1)
            out["depth"][idx] = part["depth"]
            out["acc"][idx] = part["acc"]
        self.rays = len(pixels)
        # a copy kept: what the caller gets may be changed in place without touching it
        self.last = (expression.clone(), mask, {k: v.clone() for k, v in out.items()})
        return {"rgb": out["rgb"].view(intr.h, intr.w, 3),
                "depth": out["depth"].view(intr.h, intr.w), "acc": out["acc"].view(intr.h, intr.w)}
