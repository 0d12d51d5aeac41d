"""Generic shapes for the eye and brow controls that a clip never shows.

A subject who never blinks on camera leaves the β -> mesh model nothing to fit for
eyeBlinkLeft/Right: its shape is zero, the per-control prior gives the control no region, and
a commanded blink (another person's, driving the avatar) does nothing. What a blink does is
not personal: the upper lid comes down to the lower one. So for ARKit-named eye and brow
controls that the training frames leave (nearly) still, the mesh model takes a generic
shape instead, laid out in the face's own frame (data/face_parts.face_frame: heights in units
of the mouth-to-eyes distance): the mesh guide then carries what the capture shows there
(the upper lid's skin, the brow) to where the shape puts it, so the eye narrows towards
shut in the subject's own colours, though its look is generic (on the built-in scene a
slit, where the truth shows the closed lid). Controls the clip shows keep their fitted
shapes.

Layout, in units of the mouth-to-eyes distance, from each eye's centre (y up, x across):
the eye spans |x| <= _EYE_HALF (fading out over _EYE_FADE), the skin a blink shuts
y <= _LID_UP, the brow y in [_BROW_LO, _BROW_HI] (MediaPipe's brows sit 0.13-0.32 above the
eye's centre on a real face, its upper lid near +0.05; the built-in head's lid opens to
+0.08 / -0.055).
"""

from __future__ import annotations

import numpy as np

from flamenerf.data.face_parts import face_frame, has_parts, mesh_landmarks

COVER = 0.1
"""A control whose largest training value stays below this is left to its generic shape."""

_EYE_HALF, _EYE_FADE = 0.2, 0.1
# where the lids meet in a blink; the skin up to _LID_UP shuts onto it, the skin above follows
# less and less up to _LID_TOP (below the brow). Chosen on the built-in scene without blinks
# (`synth --entangled --never eyeBlinkLeft eyeBlinkRight`, seed 0, 128 px) among
# meet -0.04 / -0.08 / -0.12, up 0.08 / 0.12, top 0.16 / 0.24: the mean share of the blinks'
# change reproduced 0.39 (0.26 with the lid's edge at 0.08; docs/decisions/generic-shapes.md)
_LID_MEET = -0.04
_LID_UP = 0.12
_LID_TOP = 0.16
_WIDE_LIFT = 0.035  # how far eyeWide lifts the upper lid
_BROW_LO, _BROW_HI, _BROW_FADE = 0.12, 0.4, 0.08
_BROW_LIFT, _BROW_DROP = 0.06, 0.05

SHAPES = ("eyeBlinkLeft", "eyeBlinkRight", "eyeWideLeft", "eyeWideRight", "browInnerUp",
          "browDownLeft", "browDownRight")
"""The controls that have a generic shape."""


def _ramp(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """0 at lo, 1 at hi, linear between, clamped (lo > hi: a falling ramp)."""
    return np.clip((x - lo) / (hi - lo), 0.0, 1.0)


def generic_basis(kind: str, names: list[str], vertices: np.ndarray,
                  landmarks: dict | None = None) -> np.ndarray | None:
    """Generic displacements of the face mesh per control (`SHAPES`; zero for the other
    controls), or None where the face's parts are unknown (data/face_parts.has_parts).
    kind, names (E,), landmarks as for `face_parts.control_weights`; vertices (V, 3) a
    typical mesh of the subject. -> (E, V, 3) float32, the mesh's units, per unit of β."""
    v = np.asarray(vertices, np.float64)
    if not has_parts(kind, names, len(v), landmarks):
        return None
    f = face_frame(v, mesh_landmarks(len(v), landmarks))
    out = np.zeros((len(names), len(v), 3))
    for side in ("Left", "Right"):
        rel = (v - f.eyes[side]) / f.scale
        y, x = rel @ f.up, rel @ f.across
        near = _ramp(np.abs(x), _EYE_HALF + _EYE_FADE, _EYE_HALF)  # this eye's columns
        # blink: the opening [_LID_MEET, _LID_UP] shuts onto _LID_MEET, the lid's skin
        # above follows less and less up to _LID_TOP
        shut = np.where(y <= _LID_UP, y - _LID_MEET,
                        (_LID_UP - _LID_MEET) * _ramp(y, _LID_TOP, _LID_UP))
        shut *= y >= _LID_MEET
        lift = _WIDE_LIFT * np.minimum(_ramp(y, 0.0, _LID_UP), _ramp(y, _LID_TOP, _LID_UP))
        brow = np.minimum(_ramp(y, _BROW_LO - _BROW_FADE, _BROW_LO),
                          _ramp(y, _BROW_HI + _BROW_FADE, _BROW_HI))
        # the inner brow: the half of the brow towards the nose
        inner = _ramp(x * (1 if side == "Left" else -1), 0.15, -0.05)
        shapes = {f"eyeBlink{side}": -shut * near, f"eyeWide{side}": lift * near,
                  f"browDown{side}": -_BROW_DROP * brow * near}
        for name, amount in shapes.items():
            if name in names:
                out[names.index(name)] += amount[:, None] * f.up * f.scale
        if "browInnerUp" in names:
            out[names.index("browInnerUp")] += ((_BROW_LIFT * brow * near * inner)[:, None]
                                                * f.up * f.scale)
    return out.astype(np.float32)


def uncovered(names: list[str], training: np.ndarray) -> list[int]:
    """Indices of the controls with a generic shape whose largest value in the training
    frames' expressions `training` (N, E) stays below `COVER`."""
    top = np.abs(np.asarray(training, np.float64)).max(0) if len(training) else np.zeros(
        len(names))
    return [k for k, n in enumerate(names) if n in SHAPES and top[k] < COVER]
