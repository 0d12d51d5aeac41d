"""Expression trajectories for the synthetic scene (ARKit-named controls in [0, 1])."""

from __future__ import annotations

import numpy as np

from flamenerf.synthetic.head import CONTROL_INDEX, CONTROLS


def _bump(t: np.ndarray, centre: float, half_width: float) -> np.ndarray:
    """Raised cosine of half-width `half_width` frames (smooth, compact)."""
    x = (t - centre) / half_width
    return np.where(np.abs(x) < 1, 0.5 * (1 + np.cos(np.pi * x)), 0.0)


def speech_trajectory(n: int, seed: int, stream: int = 0) -> np.ndarray:
    """A smooth, speech-like trajectory (n, num_controls).

    The jaw follows syllables (every 6-9 frames at 30 fps) grouped into phrases with
    pauses; lips (pucker, smile, frown), cheeks, brows and eyes have their own events, so
    several controls are active at once. Every control reaches at least 0.9 somewhere
    when n >= 60 frames. `stream` selects an independent trajectory for the same seed."""
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), 606, stream])))
    t = np.arange(n, dtype=np.float64)
    e = np.zeros((n, len(CONTROLS)))

    def add(name: str, centre: float, hw: float, amp: float) -> None:
        e[:, CONTROL_INDEX[name]] += amp * _bump(t, centre, hw)

    # jaw: syllables within phrases
    pos = rng.uniform(0, 8)
    while pos < n + 10:
        phrase_end = pos + rng.uniform(25, 70)
        while pos < phrase_end:
            gap = rng.uniform(6, 9)
            add("jawOpen", pos, gap * 0.75, rng.uniform(0.25, 1.0))
            pos += gap
        pos += rng.uniform(8, 25)

    def events(names, every: tuple[float, float], hw: tuple[float, float], amp=(0.4, 1.0),
               mirror: float = 0.0) -> None:
        pos = rng.uniform(0, every[1])
        while pos < n + hw[1]:
            h = rng.uniform(*hw)
            a = rng.uniform(*amp)
            if mirror and len(names) == 2:
                asym = rng.uniform(-mirror, mirror)
                add(names[0], pos, h, a * min(1.0, 1 + asym))
                add(names[1], pos, h, a * min(1.0, 1 - asym))
            else:
                add(names[rng.integers(len(names))], pos, h, a)
            pos += rng.uniform(*every)

    events(["mouthSmileLeft", "mouthSmileRight"], (50, 110), (15, 35), mirror=0.6)
    events(["mouthFrownLeft", "mouthFrownRight"], (70, 140), (10, 20), mirror=0.8)
    events(["mouthPucker"], (40, 90), (6, 12))
    events(["cheekPuff"], (80, 160), (8, 15))
    events(["browInnerUp"], (45, 100), (10, 25))
    events(["browDownLeft", "browDownRight"], (60, 120), (10, 25), mirror=0.5)
    events(["eyeWideLeft", "eyeWideRight"], (70, 140), (8, 18), mirror=0.3)
    # blinks: quick, both eyes, sometimes a wink
    pos = rng.uniform(5, 40)
    while pos < n + 4:
        h = rng.uniform(2.5, 4.0)
        if rng.uniform() < 0.85:
            add("eyeBlinkLeft", pos, h, 1.0)
            add("eyeBlinkRight", pos, h, 1.0)
        else:
            add(["eyeBlinkLeft", "eyeBlinkRight"][rng.integers(2)], pos, h, 1.0)
        pos += rng.uniform(45, 110)
    # make sure every control is exercised strongly at least once
    if n >= 60:
        for k, name in enumerate(CONTROLS):
            if e[:, k].max() < 0.9:
                hw = 3.5 if name.startswith("eyeBlink") else 10.0
                add(name, rng.uniform(hw, n - hw), hw, 1.0)
    return np.clip(e, 0.0, 1.0).astype(np.float32)


GROUPS: dict[str, tuple[str, ...]] = {
    "surprise": ("browInnerUp", "eyeWideLeft", "eyeWideRight", "jawOpen"),
    "smile": ("mouthSmileLeft", "mouthSmileRight", "cheekPuff"),
    "speech": ("jawOpen", "mouthPucker"),
    "anger": ("browDownLeft", "browDownRight", "mouthFrownLeft", "mouthFrownRight"),
    "blink": ("eyeBlinkLeft", "eyeBlinkRight"),
}
"""What the entangled capture moves together, each member by the same amount, as people
do: the brows rise only in a surprise, the smile comes with the cheeks, the jaw speaks with
the lips, both eyes blink. Every control is in a group; jawOpen is in two."""

PAIRS: tuple[tuple[str, str], ...] = (
    ("jawOpen", "browDownLeft"),
    ("mouthSmileLeft", "browInnerUp"),
    ("mouthPucker", "eyeWideRight"),
    ("cheekPuff", "mouthFrownRight"),
    ("mouthSmileRight", "eyeWideLeft"),
)
"""Pairs of controls from groups that the entangled capture never shows together."""


def entangled_trajectory(n: int, seed: int) -> np.ndarray:
    """A capture that moves the controls only in `GROUPS` (n, num_controls): one
    expression at a time (surprise, smile, a phrase of speech, anger, in a random order,
    each group's members by the same amount; every group at full strength the first time
    it comes, and all four within about the first 150 frames), with both eyes blinking over
    any of them. So no control ever moves alone and the groups never meet, except the
    blinks."""
    rng = np.random.Generator(np.random.PCG64(np.random.SeedSequence([int(seed), 707])))
    t = np.arange(n, dtype=np.float64)
    e = np.zeros((n, len(CONTROLS)))

    def add(group: str, centre: float, hw: float, amp: float) -> None:
        for name in GROUPS[group]:
            e[:, CONTROL_INDEX[name]] += amp * _bump(t, centre, hw)

    pos, seen, order = rng.uniform(0, 6), set(), []

    def amp(group: str, lo: float) -> float:  # the first time a group comes: full strength
        return 1.0 if group not in seen else rng.uniform(lo, 1.0)

    while pos < n + 10:
        if not order:  # each cycle shows every group once, in a new order
            order = [str(g) for g in rng.permutation(["surprise", "smile", "speech", "anger"])]
        group = order.pop()
        if group == "speech":  # syllables: the jaw and the lips together
            end = pos + rng.uniform(25, 50)
            while pos < end:
                gap = rng.uniform(6, 9)
                add("speech", pos + gap * 0.75, gap * 0.75, amp(group, 0.3))
                seen.add(group)
                pos += gap
            pos += gap * 0.75
        else:
            hw = rng.uniform(8, 16)
            add(group, pos + hw, hw, amp(group, 0.5))
            pos += 2 * hw
        seen.add(group)
        pos += rng.uniform(2, 8)
    pos = rng.uniform(5, 30)
    while pos < n + 4:
        add("blink", pos, rng.uniform(2.5, 4.0), 1.0)
        pos += rng.uniform(40, 90)
    return np.clip(e, 0.0, 1.0).astype(np.float32)


def leakage_sweep(steps: int = 3) -> tuple[np.ndarray, list[tuple[str, float]]]:
    """Neutral, then each control alone at 1/steps, 2/steps, ..., 1.

    -> expressions (1 + steps * num_controls, num_controls), and (control, value) labels
    ("neutral", 0.0) for the first."""
    exprs = [np.zeros(len(CONTROLS), np.float32)]
    labels: list[tuple[str, float]] = [("neutral", 0.0)]
    for k, name in enumerate(CONTROLS):
        for s in range(1, steps + 1):
            x = np.zeros(len(CONTROLS), np.float32)
            x[k] = s / steps
            exprs.append(x)
            labels.append((name, s / steps))
    return np.stack(exprs), labels
