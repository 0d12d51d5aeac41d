"""Cameras of the synthetic capture: a hand-held arc around the still head, or (the
handheld variant) a phone held in front of the face, shaking in the hand.

Conventions (those of the dataset): camera-to-world 4x4 with OpenGL camera axes (x right,
y up, the camera looks down -z). A camera at (0, 0, d) looking at the origin has the
identity rotation.
"""

from __future__ import annotations

import numpy as np

from flamenerf.data.dataset import Intrinsics
from flamenerf.geometry import euler_head, look_at

DISTANCE = 0.60  # metres from the head centre
TARGET = np.array([0.0, -0.035, 0.0])  # where the camera aims (between nose and mouth)
FOCAL = 1.55  # focal length in units of the image size (vertical field of view ~36 deg)
YAW_DEG, PITCH_DEG = 25.0, 10.0
# the handheld phone: peak drift (yaw, pitch, roll) in degrees and (x, y, z) in metres, and
# the tremor's standard deviation on top; drift is smooth over HANDHELD_DRIFT_FRAMES
HANDHELD_ROT_DEG = np.array([2.7, 2.7, 1.8])
HANDHELD_SHIFT_M = np.array([0.025, 0.02, 0.015])
HANDHELD_TREMOR_DEG, HANDHELD_TREMOR_M = 0.2, 0.001
HANDHELD_DRIFT_FRAMES, HANDHELD_TREMOR_FRAMES = 25.0, 1.5


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


def handheld_path(n: int, seed: int) -> np.ndarray:
    """A phone held in the hand in front of the face: camera-to-world (n, 4, 4).

    At rest the camera is frontal at DISTANCE from TARGET (the identity rotation). It
    shakes as a hand does: a slow drift (smooth over ~HANDHELD_DRIFT_FRAMES frames, peak
    HANDHELD_ROT_DEG of yaw/pitch/roll and HANDHELD_SHIFT_M of translation) plus a tremor
    (a few frames, HANDHELD_TREMOR_DEG / _M). Rotation and translation are drawn
    independently and the camera turns about its own centre, so the orientation changes
    far more than aiming at the head from the shifted positions would (a few cm at 0.6 m
    subtend ~2 deg; at the far background, tenths of a degree)."""
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), 808])))
    drift = np.clip(_smooth_noise(rng, n, 6, corr=HANDHELD_DRIFT_FRAMES), -1.5, 1.5) / 1.5
    tremor = _smooth_noise(rng, n, 6, corr=HANDHELD_TREMOR_FRAMES)
    ang = HANDHELD_ROT_DEG * drift[:, :3] + HANDHELD_TREMOR_DEG * tremor[:, :3]
    shift = HANDHELD_SHIFT_M * drift[:, 3:] + HANDHELD_TREMOR_M * tremor[:, 3:]
    c2ws = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        # euler_head's axes are the camera's at rest: yaw about y, pitch about x, roll
        # about the optical axis (head_euler reads them back)
        c2ws[i, :3, :3] = euler_head(*ang[i])
        c2ws[i, :3, 3] = TARGET + np.array([0.0, 0.0, DISTANCE]) + shift[i]
    return c2ws
