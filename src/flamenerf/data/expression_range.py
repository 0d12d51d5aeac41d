"""The range of each control that a run's training frames cover.

A model learns what an expression control does only over the values its training frames
show. Past them it extrapolates: the expression fields are linear in β, so a keyframe
`mouthSmileRight=1` on a clip whose largest smile is 0.29 adds over three times the largest
learnt change, and the face breaks into patches instead of smiling more (seen on the shared
expressions clip: smiles, browInnerUp and eyeWide at 1 against training maxima of
0.17-0.54). What users
command (keyframes, expression files, a driving video, the viewer's sliders) is therefore
clamped to this range by default — the largest smile the clip shows, not a broken face —
with a note saying what was clamped; `render --extrapolate` and the viewer's checkbox
render values as given.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ExpressionRange:
    names: list[str]
    lo: np.ndarray
    """(E,) each control's smallest value in the training frames."""
    hi: np.ndarray
    """(E,) its largest."""

    def clamp(self, values: np.ndarray) -> np.ndarray:
        """values (..., E) -> the same, each control within [lo, hi]."""
        v = np.asarray(values)
        return np.clip(v, self.lo, self.hi).astype(v.dtype, copy=False)

    def beyond(self, values: np.ndarray, tol: float = 0.02) -> list[str]:
        """values (..., E) -> what `clamp` changes, one line per control that leaves the
        range by more than `tol` (smaller clamps are applied but not worth a line):
        'name 1.00 asked, 0.10 rendered (the clip: 0.00-0.10)'."""
        v = np.asarray(values, np.float64).reshape(-1, len(self.names))
        out = []
        for k, name in enumerate(self.names):
            top, bottom = v[:, k].max(), v[:, k].min()
            if top > self.hi[k] + tol or bottom < self.lo[k] - tol:
                far = top if top - self.hi[k] >= self.lo[k] - bottom else bottom
                got = self.hi[k] if far > self.hi[k] else self.lo[k]
                out.append(f"{name} {far:.2f} asked, {got:.2f} rendered "
                           f"(the clip: {self.lo[k]:.2f}-{self.hi[k]:.2f})")
        return out

    def uncovered(self, values: np.ndarray | None = None, controls: list[int] | None = None,
                  reach: float = 0.2) -> list[str]:
        """The controls the training frames never move (their range narrower than
        MIN_SPAN) that are asked for: in `values` (..., E) beyond their range by more than
        `reach`, or the columns `controls` (an edit's). A model has learnt nothing of
        such a control, so whatever is asked of it renders near the clip's range."""
        flat = None if values is None else np.asarray(values, np.float64).reshape(
            -1, len(self.names))
        out = []
        for k, name in enumerate(self.names):
            if self.hi[k] - self.lo[k] >= MIN_SPAN:
                continue
            asked = (controls is not None and k in controls) or (
                flat is not None and (flat[:, k].max() > self.hi[k] + reach
                                      or flat[:, k].min() < self.lo[k] - reach))
            if asked:
                out.append(name)
        return out

    @staticmethod
    def not_covered_note(names: list[str], what: str) -> str:
        """The line that says which of `what`'s controls the clip never shows."""
        shown = ", ".join(names[:6]) + (", ..." if len(names) > 6 else "")
        return (f"the training frames never move {shown}: {what} stays near the clip's "
                "range there (film them to have them)")

    @staticmethod
    def generic_note(names: list[str]) -> str:
        """The line that says which asked-for controls take a generic shape."""
        return (f"the training frames never move {', '.join(names)}: a generic shape stands "
                "in for them (the clip's own skin, moved as a generic blink or brow moves)")

    @staticmethod
    def note(over: list[str], how: str = "--extrapolate renders them as given") -> str:
        """The one line that says what was clamped (`beyond`'s lines); `how`: what a user
        gives to have them as asked, or where the clamp comes from."""
        return ("clamped to the range the training frames cover, where the model has "
                f"learnt them ({how}): {'; '.join(over)}")

    @classmethod
    def of(cls, names: list[str], expressions: np.ndarray) -> "ExpressionRange":
        """The range of training expressions (N, E)."""
        x = np.asarray(expressions, np.float64)
        return cls(list(names), x.min(0), x.max(0))


SPAN_QUANTILES = (5.0, 95.0)
MIN_SPAN = 0.1


def span(values: np.ndarray, quantiles: tuple[float, float] = SPAN_QUANTILES):
    """The part of its range a control covers in most frames: its 5th and 95th percentile
    over values (N,) (floats), or each column's over (N, E) (arrays). What `eval` sweeps,
    and what `preprocess` reports; `render --expressions tour` asks for other quantiles."""
    lo, hi = np.percentile(np.asarray(values, np.float64), quantiles, axis=0)
    return (float(lo), float(hi)) if np.ndim(lo) == 0 else (lo, hi)


def varies(values: np.ndarray) -> bool:
    """Whether a control moves enough in the frames (N,) for a model to learn it: its
    5th-95th percentile span is at least MIN_SPAN."""
    lo, hi = span(values)
    return hi - lo >= MIN_SPAN


def training_expressions(ds) -> np.ndarray:
    """A dataset's training frames' expressions (N, E), in its control order."""
    return ds.expression_matrix(ds.training_frames())


def training_range(ds, generic: list[int] | tuple[int, ...] = ()) -> ExpressionRange:
    """The range of a dataset's training frames; the controls `generic` (a run's
    `FlameNeRF.generic_controls`: generic shapes stand in for them) reach up to 1."""
    rng = ExpressionRange.of(ds.expression_names, training_expressions(ds))
    for k in generic:
        rng.hi[k] = max(float(rng.hi[k]), 1.0)
    return rng
