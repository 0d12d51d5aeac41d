"""Ray sampling and volume rendering as batched pure functions (shapes in docstrings)."""

from __future__ import annotations

import torch
from torch import Tensor


def stratified_samples(near: float, far: float, num_rays: int, num: int, jitter: bool,
                       device=None, generator: torch.Generator | None = None) -> Tensor:
    """Sample ray parameters in [near, far]: -> t (num_rays, num), sorted."""
    edges = torch.linspace(near, far, num + 1, device=device)
    lo, hi = edges[:-1], edges[1:]
    if jitter:
        u = torch.rand(num_rays, num, device=device, generator=generator)
    else:
        u = torch.full((num_rays, num), 0.5, device=device)
    return lo + (hi - lo) * u


def exclusive_cumsum(x: Tensor) -> Tensor:
    """(n, s) -> (n, s): the sum of each row's entries before each entry (the optical depth
    in front of each sample). On a GPU one float64 product with a strictly upper triangular
    matrix (exact to float32, whatever TF32 setting is on): in an H200's profile of a 256 px
    frame CUDA's scan over many short rows took 0.38 ms a call; the product alone was not
    timed (the frame of docs/bench/render_gpu_h200_20261126.md includes it)."""
    if x.is_cuda:
        s = x.shape[1]
        tri = torch.ones(s, s, dtype=torch.float64, device=x.device).triu(1)
        return (x.double() @ tri).to(x.dtype)
    return torch.cumsum(torch.cat([torch.zeros_like(x[:, :1]), x[:, :-1]], 1), 1)


def render_weights(sigma: Tensor, deltas: Tensor) -> Tensor:
    """w_i = T_i (1 − exp(−σ_i δ_i)), T_i = exp(−Σ_{j<i} σ_j δ_j). (R, S) -> (R, S)."""
    sd = sigma * deltas
    alpha = 1.0 - torch.exp(-sd)
    return alpha * torch.exp(-exclusive_cumsum(sd))


def sample_pdf(bins: Tensor, weights: Tensor, num: int, jitter: bool,
               generator: torch.Generator | None = None, stratified: bool = False) -> Tensor:
    """Inverse-CDF samples from the piecewise-constant pdf `weights` (R, B) over `bins`
    (R, B+1). -> (R, num), detached (NeRF's hierarchical sampling).

    `stratified`: one sample per equal-probability stratum of the CDF (jittered inside it
    when `jitter`, its middle otherwise) instead of NeRF's independent uniform draws. With
    few samples, independent draws leave large gaps between neighbours: on the built-in
    scene, `fast` (24 samples from the proposal) scored 25.5 dB held-out after 10 minutes
    with independent draws and 27.3 dB stratified (docs/presets.md).
    """
    w = weights.detach() + 1e-5
    pdf = w / w.sum(-1, keepdim=True)
    # (0, p0, p0 + p1, ..., Σp) through exclusive_cumsum: on a CPU the same sums in the same
    # order as cat(0, cumsum(pdf)); on a GPU one product instead of CUDA's scan over short
    # rows, which took 1.5 ms of an H100's 512 px frame (cumsum in
    # docs/bench/gpu_h100_20261126_prof512.txt)
    cdf = exclusive_cumsum(torch.cat([pdf, torch.zeros_like(pdf[:, :1])], -1))
    if stratified:
        k = torch.arange(num, device=cdf.device, dtype=cdf.dtype)
        off = (torch.rand(cdf.shape[0], num, device=cdf.device, generator=generator)
               if jitter else torch.full((cdf.shape[0], num), 0.5, device=cdf.device))
        u = (k + off) / num
    elif jitter:
        u = torch.rand(cdf.shape[0], num, device=cdf.device, generator=generator)
    else:
        u = torch.linspace(0.0, 1.0, num, device=cdf.device).expand(cdf.shape[0], num)
    u = u.contiguous()
    idx = torch.searchsorted(cdf, u, right=True).clamp(1, cdf.shape[-1] - 1)
    c0, c1 = cdf.gather(-1, idx - 1), cdf.gather(-1, idx)
    b0, b1 = bins.gather(-1, idx - 1), bins.gather(-1, idx)
    frac = (u - c0) / (c1 - c0).clamp_min(1e-8)
    return (b0 + frac * (b1 - b0)).detach()


def composite(weights: Tensor, rgb: Tensor, t: Tensor, background: float = 0.0) -> dict:
    """weights (R, S), rgb (R, S, 3), t (R, S) -> rgb (R, 3), depth (R,), acc (R,).

    Depth is the weight-averaged t over the accumulated opacity (z-depth; see data/rays.py).
    """
    acc = weights.sum(-1)
    out_rgb = (weights[..., None] * rgb).sum(-2) + background * (1 - acc[..., None])
    depth = (weights * t).sum(-1) / acc.clamp_min(1e-6)
    return {"rgb": out_rgb, "depth": depth, "acc": acc}


def interlevel_loss(edges_main: Tensor, w_main: Tensor, edges_prop: Tensor,
                    w_prop: Tensor) -> Tensor:
    """mip-NeRF 360's proposal loss: the proposal's weights, summed over the proposal
    intervals that overlap each main interval, must bound the (detached) main weights.

    edges_main (R, M+1), w_main (R, M), edges_prop (R, P+1), w_prop (R, P) -> scalar.
    """
    cw = torch.cat([torch.zeros_like(w_prop[:, :1]), torch.cumsum(w_prop, -1)], -1)
    p = w_prop.shape[-1]
    lo = (torch.searchsorted(edges_prop.contiguous(), edges_main[:, :-1].contiguous(),
                             right=True) - 1).clamp(0, p)
    hi = torch.searchsorted(edges_prop.contiguous(), edges_main[:, 1:].contiguous(),
                            right=False).clamp(0, p)
    bound = cw.gather(-1, hi) - cw.gather(-1, lo)
    w = w_main.detach()
    return (torch.clamp(w - bound, min=0) ** 2 / (w + 1e-7)).sum(-1).mean()
