"""Rendering built for inference: the same model and the same samples as
`FlameNeRF.forward`, evaluated without the training path's bookkeeping.

What differs from the training forward (measured on the trained `fast` run of the built-in
scene, 256 px, 2-core CPU; docs/bench/render.md):
- no autograd, no interlevel loss, deterministic (mid-interval) samples;
- rays in chunks of 2048 on a CPU (`RenderSettings.chunk`; 8192 were once 2x slower);
- early ray termination: samples are evaluated front to back in groups, and a ray stops
  once its transmittance is below ε — its remaining samples could add at most ε to any
  output; the proposal stops likewise (skipping ~20 % of its samples), and a ray the
  proposal finds empty (opacity < ε) skips the main field;
- for one ω per batch (an image, a video with frame 0's codes, the viewer) the warp is a
  trilinear lookup of its bake instead of the MLP per sample, and rays outside the face
  silhouette read the proposal's density from its bake (model/baked.py);
- on a CPU, each MLP layer is one oneDNN matmul with bias and ReLU fused in (model/mlp.py);
  the expression fields are contracted with β inside the hash grid's kernel
  (`HashGrid.contract`);
- on CUDA the fields run in half precision (autocast; the warp and compositing stay in
  float32), the main field's features go into one half-precision buffer and both its heads
  run in one Triton kernel (`gpu_kernels.field_heads`: 512 px at 33 fps on an H200 against
  30 with the PyTorch heads), the other layers as one BLAS call
  each (`MLP.forward_lean`; `runtime.gpu_inference` decides); on a CPU with native bfloat16
  the MLP layers run in bfloat16 where that is measured to be faster (`mlp.bf16_pays`);
- the main samples are left in the order the stratified inverse CDF gives them (sorted);
- the viewer's settings (`VIEWER`) take fewer of the main field's samples than training
  placed (`RenderSettings.main_fraction`); `FAST` takes them all.

Like the training forward outside training, a ray that the proposal sampler's main samples
leave unfinished where the proposal says it ends is rendered again with more samples
(`SamplerConfig.refine_main`); here from the first pass's proposal weights, in the same call.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from flamenerf import cpu_kernels
from flamenerf.data.rays import RayBatch
from flamenerf.model.baked import baked_proposal_logits, baked_warp
from flamenerf.model.field import trunc_exp
from flamenerf.model.mlp import fused_cpu_inference
from flamenerf.model.render import composite, exclusive_cumsum, sample_pdf, stratified_samples


@dataclass(frozen=True)
class RenderSettings:
    """How `render_image` evaluates a model."""

    fast: bool = True
    """The inference path (this module); False: the training forward, exactly."""
    chunk: int = 0
    """Rays per batch; 0: 2048 on a CPU; on a GPU 262144 for a hash-grid field (a 512 px
    frame in one pass: each pass has a fixed cost of launches and synchronisations) and
    65536 for the paper's MLP fields (at 128 samples of 256-wide layers a larger pass
    would need tens of GB). On a CPU 4096 was as
    fast under the allocator `flamenerf` tunes (runtime.py), but at `fast`'s 32 samples a
    layer's 64-wide activations for 4096 rays are 32 MiB, the size from which glibc's
    default allocator maps and unmaps every such buffer: a library user's 256 px frame took
    ~35 % longer (docs/bench/render_ab_chunk2048*.json)."""
    min_transmittance: float = 1e-4
    """ε: a ray stops once less than this much light can still reach its samples."""
    group: int = 16
    """Samples per ray evaluated between two termination checks (both levels of the
    coarse/fine sampler's, and the proposal's where `proposal_group` says so; the proposal
    sampler's main samples go in one group: see `_render_rays`)."""
    proposal_group: int = 0
    """The proposal's group; 0: `group` on a CPU, the whole ray on a GPU, where each check
    waits for the device, longer than the proposal's few skipped samples would take."""
    warp_grid: int = 128
    """Vertices per axis of the baked warp for a fixed ω; 0: the exact warp MLP."""
    proposal_grid: int = 192
    """Vertices per axis of the baked proposal density of rays with 𝕀β = 0; 0: exact.
    Finer than the proposal's finest level (128 cells in `fast`): baked at 128 vertices the
    logits of a trained `fast` run lost detail between them, and samples went elsewhere
    (−0.16 dB against the reference renderer, 192: −0.002; docs/results.md)."""
    main_fraction: float = 1.0
    """Main-field samples per ray of the proposal sampler, as a fraction of the model's own
    (its training count). The viewer takes fewer (`VIEWER`)."""
    half: bool = True
    """Half precision where the device has it natively: the fields in float16 on CUDA, the
    MLP layers in bfloat16 on CPUs with AVX-512 BF16 or AMX where measured faster than
    float32 (model/mlp.py)."""

    threads: int = 0
    """On a CPU: Python threads that render chunks side by side, each with one torch thread
    (runtime.map_single_threaded); 0: as many as torch's CPU threads; 1: one thread driving
    all of them. Only the inference path (`fast`) uses more than one."""

    def render_threads(self, device: torch.device) -> int:
        if not self.fast or device.type != "cpu":
            return 1
        return self.threads if self.threads > 0 else torch.get_num_threads()

    def rays_per_chunk(self, device: torch.device, model) -> int:
        if self.chunk > 0:
            return self.chunk
        if device.type == "cpu":
            return 2048
        return 1 << 16 if model.cfg.field.kind == "mlp" else 1 << 18

    def proposal_samples_per_check(self, device: torch.device, samples: int) -> int:
        if self.proposal_group > 0:
            return self.proposal_group
        return self.group if device.type == "cpu" else samples


FAST = RenderSettings()
"""The inference path with its defaults (`flamenerf render`, eval's sweeps and drive)."""
REFERENCE = RenderSettings(fast=False, chunk=8192)
"""The training forward in chunks of 8192 rays: what eval measures."""
VIEWER = RenderSettings(main_fraction=0.75)
"""The viewer's: 24 main samples instead of `fast`'s 32 make a 128 px update ~23 % faster
on the 2-core CPU (335 -> 259 ms) for 0.12 dB against the reference renderer
(docs/bench/render_viewer_samples.md)."""


Evaluate = Callable[[Tensor, int, int], tuple[Tensor, Tensor | None]]


def march(evaluate: Evaluate, deltas: Tensor, group: int, eps: float,
          live: Tensor | None = None, colour: bool = True) -> tuple[Tensor, Tensor | None]:
    """Front-to-back volume rendering that stops evaluating a ray once its transmittance
    falls below `eps`.

    evaluate(rows (n,) long, lo, hi) -> σ (n, hi-lo) and rgb (n, hi-lo, 3) (or None) of
    samples lo..hi-1 of those rays; deltas (R, S); live (R,) bool: rays to render at all.
    -> weights (R, S) as `render.render_weights` gives them, 0 for samples never evaluated
    (each of those weighs less than eps, and together they weigh less than eps), and
    rgb (R, S, 3) with 0 there (None when `colour` is False).
    """
    R, S = deltas.shape
    weights = deltas.new_zeros(R, S)
    rgb = deltas.new_zeros(R, S, 3) if colour else None
    depth = deltas.new_zeros(R)  # optical depth so far, Σ σδ: T = exp(-depth)
    rows = (torch.arange(R, device=deltas.device) if live is None
            else live.nonzero()[:, 0])
    stop = -math.log(eps) if eps > 0 else math.inf
    for lo in range(0, S, group):
        if rows.numel() == 0:
            break
        hi = min(lo + group, S)
        sigma, c = evaluate(rows, lo, hi)
        sd = sigma.float() * deltas[rows, lo:hi]
        # the optical depth in front of each sample, summed as render_weights sums it
        before = depth[rows, None] + exclusive_cumsum(sd)
        weights[rows, lo:hi] = (1.0 - torch.exp(-sd)) * torch.exp(-before)
        if colour:
            rgb[rows, lo:hi] = c.float()
        if hi == S:  # no samples left: filtering would only wait for the device
            break
        d = before[:, -1] + sd[:, -1]
        depth[rows] = d
        rows = rows[d < stop]
    return weights, rgb


def _autocast(device: torch.device, settings: RenderSettings):
    if device.type == "cuda" and settings.half:
        return torch.autocast("cuda", dtype=torch.float16)
    return contextlib.nullcontext()


def _bakes_warp(model, settings: RenderSettings) -> bool:
    return model.warp is not None and settings.warp_grid > 0 and not model.warp_expression


def _bakes_proposal(model, settings: RenderSettings) -> bool:
    return model.cfg.sampler.kind == "proposal" and settings.proposal_grid > 0


def prepare(model, deform_code: Tensor, settings: RenderSettings) -> None:
    """Make, in this thread, what every chunk of rays with the code ω (D,) shares: the bakes
    and the CPU kernels. Before chunks render side by side (model/render_image.py), so that
    they do not each make them, and so that the bakes use every CPU thread."""
    if not settings.fast:
        return
    dev = deform_code.device
    with torch.inference_mode():
        if _bakes_warp(model, settings):
            baked_warp(model, deform_code, settings.warp_grid)
        if _bakes_proposal(model, settings):
            baked_proposal_logits(model.proposal, settings.proposal_grid, dev)
    if dev.type == "cpu":

        cpu_kernels.kernel_library()


def _warp_fn(model, rays: RayBatch, settings: RenderSettings):
    """points (n, k, 3), rows (n,) -> canonical points: the bake when every ray has the same
    ω, else the warp MLP."""
    if model.warp is None:
        return lambda xn, rows, e: xn
    codes = rays.deform_code
    # an expanded code (render_image's) is one code by construction: comparing its rows
    # would wait for the device
    if _bakes_warp(model, settings) and (codes.stride(0) == 0
                                         or bool((codes == codes[:1]).all())):
        baked = baked_warp(model, codes[0], settings.warp_grid)
        return lambda xn, rows, e: baked(xn)
    return lambda xn, rows, e: model.warp_points(xn, codes[rows, None], e)


@torch.inference_mode()
def render_rays(model, rays: RayBatch, settings: RenderSettings = FAST
                ) -> dict[str, Tensor]:
    """The inference path of FlameNeRF.forward (jitter off). -> rgb (R, 3), depth (R,),
    acc (R,), num_samples (evaluations of the radiance fields, not the proposal; 0-d)."""
    with fused_cpu_inference(bf16=settings.half):
        return _render_rays(model, rays, settings)


def _render_rays(model, rays: RayBatch, settings: RenderSettings) -> dict[str, Tensor]:
    expr = model.expression.masked(rays.expression, rays.face_ray)
    inside = model.expression.inside(rays.face_ray)
    dev = rays.origins.device
    warp = _warp_fn(model, rays, settings)
    scale = rays.dirs.norm(dim=-1, keepdim=True) / model.half_extent
    counted = []

    def points(rows, t):
        return model.proposal_points(rays.origins[rows], rays.dirs[rows],
                                     t.expand(len(rows), -1), sub_ray(rays.head, rows))

    def sub_ray(v, rows):
        return None if v is None else v[rows]

    def sub(v, rows):
        return None if v is None else v[rows, None]

    def field_at(field, t: Tensor, ray_of: Tensor | None = None) -> Evaluate:
        """The field at depths t (n, S) of rays `ray_of` (n,) (None: every ray)."""
        def evaluate(rows, lo, hi):
            depths = t[rows, lo:hi]
            if ray_of is not None:
                rows = ray_of[rows]
            xn, d, e = model.sample_points(rays.origins[rows], rays.dirs[rows],
                                           depths, sub_ray(expr, rows),
                                           sub_ray(rays.head, rows), sub_ray(inside, rows))
            counted.append(xn.shape[0] * xn.shape[1])
            xc = warp(xn, rows, e)  # in float32: a half-precision warp would move points
            with _autocast(dev, settings):
                return field(xc, d[:, None], rays.appearance_code[rows, None], e)
        return evaluate

    eps, group = settings.min_transmittance, settings.group
    s = model.cfg.sampler
    R = len(rays)
    if s.kind == "proposal":
        P = s.num_proposal
        edges_p = torch.linspace(model.near, model.far, P + 1, device=dev)
        t_p = stratified_samples(model.near, model.far, 1, P, False, dev)[0]

        baked = (baked_proposal_logits(model.proposal, settings.proposal_grid, dev)
                 if _bakes_proposal(model, settings) else None)
        zero = (torch.ones(R, dtype=torch.bool, device=dev) if expr is None
                else (expr == 0).all(-1))

        def proposal(rows, lo, hi):
            xn = points(rows, t_p[lo:hi])
            if baked is None:
                with _autocast(dev, settings):
                    return model.proposal.density(xn, sub(expr, rows)), None
            # rays with β = 0 first: one wait for the device (the count) splits them
            z = zero[rows]
            order = torch.argsort((~z).to(torch.uint8), stable=True)
            k = int(z.sum())
            flat, full = order[:k], order[k:]
            sigma = xn.new_empty(xn.shape[:2])
            if k:
                sigma[flat] = trunc_exp(baked(xn[flat].reshape(-1, 3)).view(-1, hi - lo))
            if k < len(rows):
                with _autocast(dev, settings):
                    sigma[full] = model.proposal.density(xn[full],
                                                         expr[rows[full], None]).float()
            return sigma, None

        w_p, _ = march(proposal, (edges_p[1:] - edges_p[:-1]) * scale,
                       settings.proposal_samples_per_check(dev, P), eps, colour=False)
        edges_p = edges_p.expand(R, P + 1)

        def main_samples(rows: Tensor | None, num: int) -> tuple[Tensor, Tensor]:
            """Depths (n, num) and their intervals' lengths of rays `rows` (None: all)."""
            ep, wp = (edges_p, w_p) if rows is None else (edges_p[rows], w_p[rows])
            # stratified inverse-CDF samples without jitter come out sorted (increasing
            # quantiles of a non-decreasing CDF over increasing edges), so the training
            # forward's sort is left out: on an H100 it was ~3 % of a 512 px frame
            # (docs/bench/gpu_h100_20261126_prof512.txt, radixSortKVInPlace)
            edges = sample_pdf(ep, wp, num + 1, False, stratified=True)
            sc = scale if rows is None else scale[rows]
            return 0.5 * (edges[:, 1:] + edges[:, :-1]), (edges[:, 1:] - edges[:, :-1]) * sc

        num_main = max(1, round(settings.main_fraction * s.num_main))
        t, deltas = main_samples(None, num_main)
        # a ray the proposal sees through (opacity < ε) gets nothing from the main field.
        # Its samples go in one group: placed by the proposal's weights, they end where the
        # ray's weight ends, so that (trained `fast`, built-in scene, 256 px) groups of 16
        # skipped 0.01 % of the main samples and only added a second pass of per-call work
        # (one group: 1.24 -> 1.11 s median per frame, 2 threads, frames alternated)
        w, rgb = march(field_at(model.field, t), deltas, num_main, eps,
                       live=w_p.sum(-1) >= eps)
        out = composite(w, rgb, t, model.background)
        if s.refine_main > 0:
            # FlameNeRF._refine_unfinished: rays the proposal ends and the main samples
            # leave unfinished, again with more samples from the same weights
            redo = s.unfinished(out["acc"], w_p.sum(-1))
            if len(redo):
                num = max(1, round(settings.main_fraction * s.refine_main))
                t2, deltas2 = main_samples(redo, num)
                w2, rgb2 = march(field_at(model.field, t2, redo), deltas2, num, eps)
                again = composite(w2, rgb2, t2, model.background)
                for k in ("rgb", "depth", "acc"):
                    out[k] = out[k].index_put((redo,), again[k])
    else:
        t_c = stratified_samples(model.near, model.far, R, s.num_coarse, False, dev)
        w_c, _ = march(field_at(model.field_coarse, t_c), model._deltas(t_c, rays.dirs, 1e10),
                       group, eps, colour=False)
        mids = 0.5 * (t_c[:, 1:] + t_c[:, :-1])
        t = sample_pdf(mids, w_c[:, 1:-1], s.num_fine, False)
        t, _ = torch.sort(torch.cat([t_c, t], -1) if s.fine_reuses_coarse else t, -1)
        w, rgb = march(field_at(model.field, t), model._deltas(t, rays.dirs, 1e10), group, eps)
        out = composite(w, rgb, t, model.background)
    out["num_samples"] = torch.tensor(sum(counted))
    return out

