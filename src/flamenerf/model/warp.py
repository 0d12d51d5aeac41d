"""The Nerfies SE(3) deformation field D(x; ω): observation space -> canonical space."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from flamenerf.config import WarpConfig
from flamenerf.model.encodings import cosine_easing_window, pe_dim, positional_encoding
from flamenerf.model.mlp import MLP
from flamenerf.model.se3 import apply_se3


class SE3Field(nn.Module):
    """MLP(γ_α(x), ω) -> screw axis (w, v); x' = exp([S]) x. α anneals the PE bands."""

    def __init__(self, cfg: WarpConfig, cond_dim: int = 0):
        super().__init__()
        self.cfg = cfg
        in_dim = pe_dim(3, cfg.num_freqs) + cfg.code_dim + cond_dim
        self.trunk = MLP(in_dim, cfg.width, cfg.depth, cfg.skips)
        self.rot = nn.Linear(cfg.width, 3)
        self.trans = nn.Linear(cfg.width, 3)
        for head in (self.rot, self.trans):
            nn.init.uniform_(head.weight, -cfg.init_scale, cfg.init_scale)
            nn.init.zeros_(head.bias)
        self.register_buffer("alpha", torch.tensor(0.0))

    def set_alpha(self, alpha: float) -> None:
        self.alpha.fill_(alpha)

    def forward(self, x: Tensor, code: Tensor) -> Tensor:
        """x (*bs, 3) normalised observation points, code (*, code_dim + cond_dim) per point
        or per ray (broadcastable to *bs) -> (*bs, 3) canonical."""
        win = cosine_easing_window(self.cfg.num_freqs, self.alpha.item()).to(x)
        h = self.trunk(positional_encoding(x, self.cfg.num_freqs, win), code)
        return apply_se3(self.rot(h), self.trans(h), x)
