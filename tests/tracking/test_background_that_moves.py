"""What moves by itself, on frames whose truth is known: a textured still background with
one patch whose texture slides back and forth."""

from __future__ import annotations

import numpy as np

from flamenerf.tracking.moving_background import detect_moving


def _frames(n: int = 6, size: int = 96):
    from scipy.ndimage import gaussian_filter, shift

    rng = np.random.default_rng(0)
    still = gaussian_filter(rng.uniform(0, 255, (size, size)), 1.2)
    leaves = gaussian_filter(rng.uniform(0, 255, (size, size)), 1.2)
    patch = np.zeros((size, size), bool)
    patch[10:50, 55:90] = True
    frames = []
    for k in range(n):
        moved = shift(leaves, (0, 3.0 * np.sin(1.3 * k)), mode="wrap")
        frames.append(np.where(patch, moved, still).clip(0, 255).astype(np.uint8))
    return np.stack(frames), patch


def still_camera(a, b, x0, x1):
    return np.linalg.norm(x1 - x0, axis=1)


def test_the_sliding_patch_is_flagged_and_the_still_background_is_not():
    frames, patch = _frames()
    background = np.ones(frames.shape, bool)
    background[:, 60:, :30] = False  # the person: never flagged
    moving = detect_moving(frames, background, still_camera, 1.0)
    inner = np.zeros_like(patch)
    inner[14:46, 59:86] = True  # away from the patch's edges, where flow blurs across
    assert moving[:, inner].mean() > 0.8
    near = np.zeros_like(patch)
    near[4:56, 49:96] = True  # flow and the closing blur a few pixels across the edges
    assert moving[:, ~near].mean() < 0.005
    assert not moving[~background].any()


def test_a_still_scene_has_nothing_moving():
    frames, _ = _frames()
    frames[:] = frames[0]
    assert not detect_moving(frames, np.ones(frames.shape, bool), still_camera, 1.0).any()
