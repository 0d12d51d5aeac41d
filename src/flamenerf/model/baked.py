"""Fields baked onto dense grids for conditioning that does not change between renders.

- The deformation D(·; ω) for one code ω: while a viewer user moves the camera or a
  slider, or a video is rendered with frame 0's codes, ω is fixed and the warp is a fixed
  smooth map of the scene box. It was the largest share of a `fast` frame on a CPU (PE +
  MLP + SE(3): ~48 % of a 256 px frame); the trained `fast` run displaces points by < 1 %
  of the box, and a 128³ bake of its displacement costs 0.02 dB PSNR (docs/bench/render.md).
- The proposal's density of rays outside the face silhouette, where 𝕀β = 0: it depends on
  nothing but the weights (the proposal sees observation space, without ω), so one bake
  serves every camera, code and expression; rays through the silhouette keep the exact
  proposal of their β.

A bake is remembered on the module it was made from, keyed by the conditioning and the
parameters' in-place version counters (so a model that is still training never reuses one).
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from flamenerf import cpu_kernels


def _grid_points(n: int, device) -> Tensor:
    """The n³ vertices of [-1, 1]³, x fastest: vertex (i, j, k) at row i + j·n + k·n²."""
    lin = torch.linspace(-1.0, 1.0, n, device=device)
    z, y, x = torch.meshgrid(lin, lin, lin, indexing="ij")
    return torch.stack([x, y, z], -1).reshape(-1, 3)


class DenseGrid:
    """C values at the n³ vertices of [-1, 1]³, read by trilinear interpolation (clamped to
    the box outside it, as the hash grids clamp their input)."""

    def __init__(self, fn: Callable[[Tensor], Tensor], n: int, device, batch: int = 1 << 16):
        """fn: points (N, 3) -> values (N, C), evaluated at every vertex."""
        if n < 2:
            raise ValueError("a baked grid needs at least 2 vertices per axis")
        self.n = int(n)
        with torch.inference_mode():
            self.table = torch.cat([fn(p) for p in _grid_points(self.n, device).split(batch)]
                                   ).float().contiguous()  # (n³, C): the kernel's dense layout
        self._layout = None

    def __call__(self, x: Tensor) -> Tensor:
        """x (N, 3) -> (N, C)."""
        C = self.table.shape[1]
        if x.device.type == "cpu" and x.dtype == torch.float32:

            lib = cpu_kernels.kernel_library()
            if lib is not None:
                # one dense level of the hash-grid kernel is exactly this interpolation
                u = ((x + 1.0) * 0.5).contiguous()
                out = torch.empty(x.shape[0], C)
                if self._layout is None:
                    self._layout = ((ctypes.c_int64 * 1)(self.n - 1), (ctypes.c_uint8 * 1)(1),
                                    (ctypes.c_void_p * 1)(self.table.data_ptr()))
                res, dense, tables = self._layout
                lib.hashgrid_forward(u.data_ptr(), x.shape[0], 1, C, tables, res, dense, 0,
                                     out.data_ptr(), C, torch.get_num_threads())
                return out
        n = self.n
        vol = self.table.to(x.dtype).view(n, n, n, C).permute(3, 0, 1, 2)[None]  # (1,C,z,y,x)
        v = F.grid_sample(vol, x.view(1, -1, 1, 1, 3), mode="bilinear",
                          padding_mode="border", align_corners=True)
        return v.view(C, -1).t()


def _cached(module: nn.Module, key: tuple, make: Callable[[], DenseGrid]) -> DenseGrid:
    # one bake per module: a viewer or a video keeps one ω
    key = key + tuple((p.data_ptr(), p._version) for p in module.parameters())
    cached = getattr(module, "_baked", None)
    if cached is not None and cached[0] == key:
        return cached[1]
    grid = make()
    module._baked = (key, grid)
    return grid


def baked_warp(model: nn.Module, code: Tensor, n: int) -> Callable[[Tensor], Tensor]:
    """FlameNeRF.warp_points (without β) for one code ω (code_dim,) as x + D̃(x): points
    (*bs, 3) -> canonical (*bs, 3)."""
    warp = model.warp
    key = ("warp", n, str(code.device), float(warp.alpha), model.warp_in_head,
           model.cfg.warp.band, tuple(code.detach().float().cpu().tolist()))
    grid = _cached(warp, key, lambda: DenseGrid(lambda p: model.warp_points(p, code[None]) - p,
                                                n, code.device))

    def apply(x: Tensor) -> Tensor:
        flat = x.reshape(-1, 3)
        return (flat + grid(flat)).view(x.shape)

    return apply


def baked_proposal_logits(proposal: nn.Module, n: int, device) -> DenseGrid:
    """The ProposalField's pre-activation density at 𝕀β = 0 (ProposalField.raw_density),
    baked: points (N, 3) -> (N, 1)."""
    return _cached(proposal, ("proposal", n, str(device)),
                   lambda: DenseGrid(lambda p: proposal.raw_density(p, None)[..., None], n,
                                     device))
