"""Head motion of the synthetic scene (`flamenerf synth --head-motion`): the head turns
and shifts on its neck independently of the camera, against a static room.

Poses are world-from-head 4x4 matrices: a rotation about the neck pivot (head axes = world
axes at rest: x the subject's left, y up, z out of the face) and a translation.
"""

from __future__ import annotations

import numpy as np

from flamenerf.geometry import euler_head
from flamenerf.synthetic.background import NECK_PIVOT
from flamenerf.synthetic.cameras import _smooth_noise

YAW_DEG, PITCH_DEG, ROLL_DEG = 25.0, 10.0, 4.0
SHIFT_M = np.array([0.02, 0.01, 0.015])  # translation amplitude per axis, metres


def head_pose(yaw: float, pitch: float, roll: float, shift=(0.0, 0.0, 0.0)) -> np.ndarray:
    """World-from-head (4, 4): turned by yaw/pitch/roll degrees (geometry.euler_head) about
    the neck pivot, then shifted by `shift` metres."""
    R = euler_head(yaw, pitch, roll)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = NECK_PIVOT - R @ NECK_PIVOT + np.asarray(shift, np.float64)
    return T


def head_motion_path(n: int, seed: int) -> np.ndarray:
    """The capture's head poses (n, 4, 4): yaw sweeps +-YAW_DEG 1.5 times, pitch +-PITCH_DEG
    2.5 times, roll +-ROLL_DEG once, with seeded phases (so unlike the camera's sweep,
    once yaw and twice pitch) and a few cm of smooth translation."""
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), 606])))
    ph = rng.uniform(0, 2 * np.pi, 3)
    s = np.arange(n) / max(n, 1)
    yaw = YAW_DEG * np.sin(2 * np.pi * 1.5 * s + ph[0])
    pitch = PITCH_DEG * np.sin(2 * np.pi * 2.5 * s + ph[1])
    roll = ROLL_DEG * np.sin(2 * np.pi * s + ph[2])
    shift = SHIFT_M * np.clip(_smooth_noise(rng, n, 3, corr=max(3.0, n / 8)), -1.5, 1.5) / 1.5
    return np.stack([head_pose(yaw[i], pitch[i], roll[i], shift[i]) for i in range(n)])


def novel_head_poses(k: int, seed: int) -> np.ndarray:
    """`k` head poses (k, 4, 4) for evaluation: (yaw, pitch, roll, shift) drawn
    independently within 80 % of the capture's ranges, so their combinations are new."""
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), 707])))
    a = rng.uniform(-0.8, 0.8, (k, 6))
    return np.stack([head_pose(YAW_DEG * r[0], PITCH_DEG * r[1], ROLL_DEG * r[2],
                               SHIFT_M * r[3:]) for r in a])
