"""Image metrics on float images in [0, 1]."""

from __future__ import annotations

import math

import numpy as np


def mse(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    d = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    if mask is not None:
        m = np.asarray(mask, bool)
        if not m.any():
            return float("nan")
        d = d[m]
    return float(d.mean())


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    m = mse(a, b, mask)
    return float("nan") if math.isnan(m) else -10.0 * math.log10(max(m, 1e-12))


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """Structural similarity of two (H, W, 3) images (scikit-image, Gaussian weights as in
    Wang et al. 2004)."""
    from skimage.metrics import structural_similarity

    return float(structural_similarity(np.asarray(a, np.float64), np.asarray(b, np.float64),
                                       channel_axis=-1, data_range=1.0, gaussian_weights=True,
                                       sigma=1.5, use_sample_covariance=False))


def mean_abs_change(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean absolute per-pixel difference on the 0-255 scale, over the pixels in `mask`
    (all channels): the background-leakage measure. NaN when the mask is empty."""
    d = np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)) * 255.0
    if mask is not None:
        m = np.asarray(mask, bool)
        if not m.any():
            return float("nan")
        d = d[m]
    return float(d.mean())
