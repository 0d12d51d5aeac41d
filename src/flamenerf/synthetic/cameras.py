"""Cameras of the synthetic capture: a hand-held arc around the still head.

Conventions (those of the dataset): camera-to-world 4x4 with OpenGL camera axes (x right,
y up, the camera looks down -z). A camera at (0, 0, d) looking at the origin has the
identity rotation.
"""

from __future__ import annotations

import numpy as np

from flamenerf.data.dataset import Intrinsics
from flamenerf.geometry import look_at

DISTANCE = 0.60  # metres from the head centre
TARGET = np.array([0.0, -0.035, 0.0])  # where the camera aims (between nose and mouth)
FOCAL = 1.55  # focal length in units of the image size (vertical field of view ~36 deg)
YAW_DEG, PITCH_DEG = 25.0, 10.0


def intrinsics(size: int) -> Intrinsics:
    f = FOCAL * size
    return Intrinsics(w=size, h=size, fx=f, fy=f, cx=size / 2, cy=size / 2)


def orbit(yaw_deg: float, pitch_deg: float, distance: float = DISTANCE,
          target: np.ndarray = TARGET, roll_deg: float = 0.0) -> np.ndarray:
    """Camera on a sphere around `target`; yaw > 0 moves it towards +x, pitch > 0 up."""
    y, p = np.deg2rad(yaw_deg), np.deg2rad(pitch_deg)
    eye = target + distance * np.array([np.sin(y) * np.cos(p), np.sin(p), np.cos(y) * np.cos(p)])
    return look_at(eye, target, roll_deg=roll_deg)


def _smooth_noise(rng: np.random.Generator, n: int, dims: int, corr: float) -> np.ndarray:
    """Unit-variance noise (n, dims) smoothed over about `corr` frames."""
    pad = int(4 * corr) + 1
    raw = rng.standard_normal((n + 2 * pad, dims))
    k = np.exp(-0.5 * (np.arange(-pad, pad + 1) / corr) ** 2)
    k /= np.sqrt((k ** 2).sum())
    return np.stack([np.convolve(raw[:, i], k, mode="valid") for i in range(dims)], -1)[:n]


def capture_path(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The capture's camera-to-world matrices (n, 4, 4) and their (yaw, pitch) in degrees.

    The camera sweeps yaw through +-YAW_DEG once and pitch through +-PITCH_DEG twice, with
    hand jitter (about 0.7 deg of aim, 4 mm of position, 1 deg of roll)."""
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), 404])))
    s = np.arange(n) / max(n, 1)
    yaw = YAW_DEG * np.sin(2 * np.pi * s)
    pitch = PITCH_DEG * np.sin(4 * np.pi * s + 0.5) - 2.0 * np.sin(0.5)  # pitch(0) ~ 2.8
    jit = _smooth_noise(rng, n, 7, corr=4.0)
    yaw_j = yaw + 0.7 * jit[:, 0]
    pitch_j = pitch + 0.7 * jit[:, 1]
    dist = DISTANCE + 0.03 * np.sin(2 * np.pi * 1.5 * s + 1.0) + 0.004 * jit[:, 2]
    roll = 1.0 * jit[:, 3]
    c2ws = []
    for i in range(n):
        tgt = TARGET + 0.004 * jit[i, 4:7]
        c2ws.append(orbit(yaw_j[i], pitch_j[i], dist[i], tgt, roll[i]))
    return np.stack(c2ws), np.stack([yaw_j, pitch_j], -1)


def novel_path(k: int, seed: int) -> np.ndarray:
    """`k` cameras (k, 4, 4) off the capture path, for re-animation: a loop around the
    outside of the capture's (yaw, pitch) range (yaw up to ~31 deg, pitch up to ~14 deg),
    at distances 0.52-0.68 m (the capture stays within 0.57-0.63 m)."""
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), 505])))
    phase = rng.uniform(0, 2 * np.pi)
    s = phase + 2 * np.pi * np.arange(k) / max(k, 1)
    c, sn = np.cos(s), np.sin(s)
    yaw = 31.0 * np.sign(c) * np.abs(c) ** 0.5
    pitch = 14.0 * np.sign(sn) * np.abs(sn) ** 0.5 - 1.0
    dist = DISTANCE + 0.08 * np.sin(2 * s + rng.uniform(0, 2 * np.pi))
    roll = rng.uniform(-2, 2, k)
    return np.stack([orbit(yaw[i], pitch[i], dist[i], TARGET, roll[i]) for i in range(k)])
