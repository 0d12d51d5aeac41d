"""Deterministic procedural noise for the synthetic scene's textures.

Value noise on an integer lattice: an integer hash (wrapping int32 arithmetic) maps each
lattice point to a value in [-1, 1]; values are blended with the quintic fade
6t^5 - 15t^4 + 10t^3. Only integer arithmetic and basic float operations are used, so a
seed gives the same texture bits on every run.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

_PRIMES = (374761393, 668265263, 1274126177)


class Noise:
    """Seeded value noise in 2 or 3 dimensions, with fractal sums."""

    def __init__(self, seed: int):
        # fold the seed into 31 bits; different seeds give unrelated hashes
        self.seed = int((int(seed) * 2654435761 + 97) % 2147483629)

    def hash(self, *coords: torch.Tensor) -> torch.Tensor:
        """Integer lattice coordinates (int32 tensors) -> values in [-1, 1] (float32)."""
        h = torch.full_like(coords[0], 0) + self.seed
        for c, prime in zip(coords, _PRIMES):
            h = h + c * prime
        h = (h ^ (h >> 13)) * 1103515245
        h = h ^ (h >> 16)
        return (h & 0xFFFF).float() * (2.0 / 65535.0) - 1.0

    def value(self, p: torch.Tensor) -> torch.Tensor:
        """Value noise at points p (..., D) with D in {2, 3}; unit lattice spacing. -> (...)."""
        pf = torch.floor(p)
        i = pf.to(torch.int32)
        f = p - pf
        w = f * f * f * (f * (f * 6 - 15) + 10)
        dim = p.shape[-1]
        ic = [i[..., k] for k in range(dim)]
        wk = [w[..., k] for k in range(dim)]
        out = torch.zeros(p.shape[:-1], dtype=p.dtype)
        for corner in range(1 << dim):
            bits = [(corner >> k) & 1 for k in range(dim)]
            weight = None
            for k, b in enumerate(bits):
                term = wk[k] if b else 1 - wk[k]
                weight = term if weight is None else weight * term
            out = out + weight * self.hash(*[ic[k] + b if b else ic[k] for k, b in enumerate(bits)])
        return out

    def fbm(self, p: torch.Tensor, octaves: int = 4, lacunarity: float = 2.0,
            gain: float = 0.5) -> torch.Tensor:
        """Fractal sum of `octaves` value-noise layers, normalised to about [-1, 1]."""
        total = torch.zeros(p.shape[:-1], dtype=p.dtype)
        amp, norm, freq = 1.0, 0.0, 1.0
        for o in range(octaves):
            # offset each octave so lattice points of different octaves do not line up
            total = total + amp * self.value(p * freq + 17.31 * (o + 1))
            norm += amp
            amp *= gain
            freq *= lacunarity
        return total / norm


def upsample(img: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """Bilinear resize of (H, W) or (C, H, W) to `shape` (for smooth, low-frequency layers
    computed on a coarse grid)."""
    x = img[None, None] if img.ndim == 2 else img[None]
    y = F.interpolate(x, size=shape, mode="bilinear", align_corners=False)
    return y[0, 0] if img.ndim == 2 else y[0]
