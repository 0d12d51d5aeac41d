"""Image files and colour maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flamenerf.training.checkpoint import atomic_write_bytes


def to_uint8(img: np.ndarray) -> np.ndarray:
    if img.dtype == np.uint8:
        return img
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def save_png(path: str | Path, img: np.ndarray) -> None:
    """Write an (H, W[, 3]) float-in-[0,1] or uint8 image atomically."""
    import imageio.v3 as iio

    data = iio.imwrite("<bytes>", to_uint8(np.asarray(img)), extension=".png")
    atomic_write_bytes(Path(path), lambda f: f.write(data))


def colorize_depth(depth: np.ndarray, lo: float | None = None, hi: float | None = None,
                   cmap: str = "turbo") -> np.ndarray:
    """(H, W) depth -> (H, W, 3) float colour image (near = warm)."""
    import matplotlib

    d = np.asarray(depth, np.float64)
    lo = np.percentile(d, 1) if lo is None else lo
    hi = np.percentile(d, 99) if hi is None else hi
    x = 1.0 - np.clip((d - lo) / max(hi - lo, 1e-9), 0, 1)
    return matplotlib.colormaps[cmap](x)[..., :3].astype(np.float32)
