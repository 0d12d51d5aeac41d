"""Input encodings: NeRF positional encoding with the Nerfies coarse-to-fine window, and a
pure-PyTorch multiresolution hash grid.

PE convention (pinned by tests): γ(x) = (x, sin(2^0 πx), cos(2^0 πx), ..., sin(2^{m-1} πx),
cos(2^{m-1} πx)), blocks ordered by frequency, sin before cos, input first; x is in the
normalised scene box [-1, 1]^3.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn


def cosine_easing_window(num_freqs: int, alpha: float | Tensor) -> Tensor:
    """Coarse-to-fine weights w_l(α) = (1 − cos(π·clamp(α − l, 0, 1))) / 2, l = 0..m−1.

    -> (num_freqs,). α = m·t/N grows with the step t; all bands are on once α ≥ m.
    """
    bands = torch.arange(num_freqs, dtype=torch.float32)
    x = torch.clamp(torch.as_tensor(alpha, dtype=torch.float32) - bands, 0.0, 1.0)
    return 0.5 * (1.0 - torch.cos(math.pi * x))


def positional_encoding(x: Tensor, num_freqs: int, window: Tensor | None = None) -> Tensor:
    """(*bs, d) -> (*bs, d + 2·d·num_freqs). `window` (num_freqs,) weights each band."""
    freqs = (2.0 ** torch.arange(num_freqs, dtype=x.dtype, device=x.device)) * math.pi
    xb = x[..., None, :] * freqs[:, None]  # (*bs, m, d)
    enc = torch.stack([torch.sin(xb), torch.cos(xb)], dim=-2)  # (*bs, m, 2, d)
    if window is not None:
        enc = enc * window.to(x)[:, None, None]
    return torch.cat([x, enc.flatten(-3)], dim=-1)


def pe_dim(d: int, num_freqs: int) -> int:
    return d + 2 * d * num_freqs


_PRIMES = (1, 2654435761, 805459861)


class HashGrid(nn.Module):
    """Multiresolution hash encoding (Müller et al. 2022) in plain PyTorch.

    The table is feature-major (F, L·T) and gathered with `index_select` over level-major
    indices (L, 8, N): the fastest layout measured on CPU (PERF_NOTES.md).
    """

    def __init__(self, levels: int = 16, features: int = 2, log2_size: int = 17,
                 base_res: int = 16, max_res: int = 1024):
        super().__init__()
        self.levels, self.features, self.size = levels, features, 2**log2_size
        growth = math.exp((math.log(max_res) - math.log(base_res)) / max(levels - 1, 1))
        res = [int(math.floor(base_res * growth**lv)) for lv in range(levels)]
        self.register_buffer("res", torch.tensor(res, dtype=torch.int64), persistent=False)
        dense = [(r + 1) ** 3 <= self.size for r in res]
        self.register_buffer("dense", torch.tensor(dense), persistent=False)
        self.table = nn.Parameter(torch.empty(features, levels * self.size).uniform_(-1e-4, 1e-4))
        corners = torch.tensor([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)])
        self.register_buffer("corners", corners, persistent=False)  # (8, 3)

    @property
    def out_dim(self) -> int:
        return self.levels * self.features

    def forward(self, x: Tensor) -> Tensor:
        """x (N, 3) in [0, 1]^3 -> (N, L·F)."""
        n = x.shape[0]
        pos = x.clamp(0, 1)[None] * self.res[:, None, None].to(x)  # (L, N, 3)
        base = torch.floor(pos.detach()).to(torch.int64)  # (L, N, 3)
        frac = pos - base  # (L, N, 3)
        c = base[:, None] + self.corners[None, :, None]  # (L, 8, N, 3)
        r1 = (self.res + 1)[:, None, None]
        dense_idx = c[..., 0] + c[..., 1] * r1 + c[..., 2] * r1 * r1
        hashed = (c[..., 0] * _PRIMES[0]) ^ (c[..., 1] * _PRIMES[1]) ^ (c[..., 2] * _PRIMES[2])
        idx = torch.where(self.dense[:, None, None], dense_idx, hashed) % self.size
        idx = idx + (torch.arange(self.levels, device=x.device) * self.size)[:, None, None]
        feats = self.table.index_select(1, idx.reshape(-1)).view(self.features, self.levels, 8, n)
        cw = self.corners[None, :, None].to(x)  # (1, 8, 1, 3)
        f = frac[:, None]  # (L, 1, N, 3)
        w = torch.where(cw > 0, f, 1 - f).prod(-1)  # (L, 8, N)
        out = (feats * w[None]).sum(2)  # (F, L, N)
        return out.permute(2, 1, 0).reshape(n, -1)
