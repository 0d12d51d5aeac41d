"""Error-guided ray sampling: a coarse map of each training frame's recent photometric error,
from which a share of every batch is drawn, so that what the model still gets wrong (a blink
seen in a few frames, the lips, the irises) gets more rays than what it already reproduces
(instant-ngp's error-map sampling for images, here over every frame of the capture)."""

from __future__ import annotations

import torch
from torch import Tensor


class ErrorMap:
    """Per-cell running mean of the squared error of the rays that fell in the cell.

    Cells are `cell` x `cell` pixels of each of `n` frames. A cell no ray has visited yet
    holds the first batch's mean error, so that it is drawn as often as an average cell."""

    def __init__(self, n: int, h: int, w: int, cell: int = 4, rate: float = 0.3):
        self.n, self.h, self.w, self.cell, self.rate = n, h, w, cell, rate
        self.gh, self.gw = -(-h // cell), -(-w // cell)
        self.err: Tensor | None = None  # (n·gh·gw,), filled at the first update

    def _cells(self, fi: Tensor, ys: Tensor, xs: Tensor) -> Tensor:
        return (fi * self.gh + ys // self.cell) * self.gw + xs // self.cell

    @torch.no_grad()
    def update(self, fi: Tensor, ys: Tensor, xs: Tensor, se: Tensor) -> None:
        """Pixels (fi, ys, xs), each (B,) long, and their rays' squared errors (B,)."""
        se = se.detach().float().cpu()
        if self.err is None:
            self.err = torch.full((self.n * self.gh * self.gw,), float(se.mean()))
        cells = self._cells(fi.cpu(), ys.cpu(), xs.cpu())
        total = torch.zeros_like(self.err).index_add_(0, cells, se)
        count = torch.zeros_like(self.err).index_add_(0, cells, torch.ones_like(se))
        hit = count > 0
        self.err[hit] += self.rate * (total[hit] / count[hit] - self.err[hit])

    def sample(self, k: int, generator: torch.Generator) -> tuple[Tensor, Tensor, Tensor]:
        """k pixels drawn with probability proportional to their cell's error (uniform
        before the first update) -> fi, ys, xs, each (k,) long."""
        if self.err is None:
            cells = torch.randint(self.n * self.gh * self.gw, (k,), generator=generator)
        else:
            cells = torch.multinomial(self.err.clamp_min(1e-12), k, replacement=True,
                                      generator=generator)
        fi, rest = cells // (self.gh * self.gw), cells % (self.gh * self.gw)
        ys = (rest // self.gw) * self.cell + torch.randint(self.cell, (k,), generator=generator)
        xs = (rest % self.gw) * self.cell + torch.randint(self.cell, (k,), generator=generator)
        return fi, ys.clamp_max(self.h - 1), xs.clamp_max(self.w - 1)
