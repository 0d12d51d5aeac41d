"""A plain ReLU MLP with NeRF-style skip connections (the input is re-concatenated)."""

from __future__ import annotations

import torch
from torch import Tensor, nn


class MLP(nn.Module):
    def __init__(self, in_dim: int, width: int, depth: int, skips: tuple[int, ...] = (),
                 out_dim: int | None = None):
        super().__init__()
        self.skips = set(skips)
        layers, d = [], in_dim
        for i in range(depth):
            if i in self.skips:
                d += in_dim
            layers.append(nn.Linear(d, width))
            d = width
        self.layers = nn.ModuleList(layers)
        self.out = nn.Linear(d, out_dim) if out_dim is not None else None
        self.out_dim = out_dim if out_dim is not None else width

    def forward(self, x: Tensor) -> Tensor:
        h = x
        for i, layer in enumerate(self.layers):
            if i in self.skips:
                h = torch.cat([h, x], -1)
            h = torch.relu(layer(h))
        return self.out(h) if self.out is not None else h
