"""A plain ReLU MLP with NeRF-style skip connections (the input is re-concatenated).

Conditioning that is the same for every sample of a ray (a frame code, an expression, a
view direction) can be passed as `cond` with a broadcastable shape, e.g. (R, 1, C) next to
samples (R, S, D). The network is the same as one fed the concatenation [x, cond] (the
weights are one Linear over both), but the conditioning's share of the first layer is
computed once per ray instead of once per sample, and no (R·S, C) copy is ever made.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def linear_of_concat(layer: nn.Linear, parts: list[Tensor]) -> Tensor:
    """layer(cat(parts, -1)) for parts whose leading dims broadcast against each other."""
    out, start = None, 0
    for p in parts:
        w = layer.weight[:, start:start + p.shape[-1]]
        start += p.shape[-1]
        y = F.linear(p, w)
        out = y if out is None else out + y
    assert start == layer.in_features, (start, layer.in_features)
    return out + layer.bias


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

    def forward(self, x: Tensor, cond: Tensor | None = None) -> Tensor:
        """x (*bs, in_dim - C), cond (*bs', C) broadcastable to x's leading dims, or None
        (then x holds the whole input) -> (*bs, out_dim)."""
        inputs = [x] if cond is None else [x, cond]
        h = None
        for i, layer in enumerate(self.layers):
            if h is None:
                h = linear_of_concat(layer, inputs)
            elif i in self.skips:
                h = linear_of_concat(layer, [h, *inputs])
            else:
                h = layer(h)
            h = torch.relu(h)
        if self.out is None:
            return h
        if h is None:  # depth 0: a single linear map of the input
            return linear_of_concat(self.out, inputs)
        return self.out(h)
