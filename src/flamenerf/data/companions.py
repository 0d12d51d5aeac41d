"""Controls a face tracker reads together, for expressions that name only some controls.

MediaPipe's blendshape scores co-vary on real faces for reasons of the tracker as much as of
the face: a closed eye reads as eyeBlink *and* eyeLookDown (correlation 0.9 on the shared
expressions clip), an open mouth as jawOpen and mouthLowerDown. A model trained on such
frames learns the closed eye from the pair; a keyframe `eyeBlinkLeft=1` that holds
eyeLookDownLeft at frame 0's value asks for an expression no training frame showed, and the
eye barely closes (re-tracked gain 0.06 on that clip). Companions move the other controls of
the named control's part of the face and side with it, by a per-subject linear regression
on the training frames, within the range those frames cover. One part and one side
(data/face_parts.py) so that a wink stays a wink and opening the jaw does not raise the
brows, which the clip's surprised faces also do.

Only ARKit-named controls on MediaPipe's mesh have parts; other expression models (FLAME's
components, the built-in scene's rig) get no companions.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from flamenerf.data.expression_range import ExpressionRange, training_expressions
from flamenerf.data.face_parts import applies, part_and_side

RIDGE = 1e-3
"""Ridge on the regressors' scatter, relative to its trace (keeps near-duplicate named
controls from producing large opposite slopes)."""


@dataclass(frozen=True)
class Companions:
    names: list[str]
    follows: np.ndarray
    """(E, E) bool: follows[k, j] when control j may move with a named control k."""
    expressions: np.ndarray
    """(N, E) the training frames' expressions the regressions are fitted on."""

    def of(self, name: str) -> list[str]:
        """The controls that move with `name` alone."""
        k = self.names.index(name)
        return [n for j, n in enumerate(self.names) if self.follows[k, j]]

    def complete(self, base: np.ndarray, values: Mapping[int, float]) -> np.ndarray:
        """base (E,) with the controls in `values` ({index: value}) set and each of their
        companions moved from base by its regression on the named controls it follows
        (fitted on the training frames, centred), clipped to its training range. -> (E,)"""
        out = self.complete_frames(np.asarray(base)[None],
                                   {k: np.array([v]) for k, v in values.items()})
        return out[0].astype(np.asarray(base).dtype, copy=False)

    def complete_frames(self, base: np.ndarray, values: Mapping[int, np.ndarray]
                        ) -> np.ndarray:
        """`complete` for T frames at once: base (T, E), values {index: (T,)} -> (T, E);
        the regressions depend only on which controls are named, so they are fitted once."""
        base = np.asarray(base, np.float64)
        out = base.copy()
        named = sorted(values)
        for k in named:
            out[:, k] = values[k]
        x = self.expressions - self.expressions.mean(0)
        rng = ExpressionRange.of(self.names, self.expressions)
        for j in range(len(self.names)):
            ks = [k for k in named if self.follows[k, j] and j not in values]
            if not ks:
                continue
            a = x[:, ks]
            gram = a.T @ a
            gram += RIDGE * max(float(np.trace(gram)), 1e-12) * np.eye(len(ks))
            coef = np.linalg.solve(gram, a.T @ x[:, j])
            step = (np.stack([values[k] for k in ks], -1) - base[:, ks]) @ coef
            out[:, j] = np.clip(base[:, j] + step, rng.lo[j], rng.hi[j])
        return out


def fit_companions(names: list[str], kind: str, num_vertices: int,
                   expressions: np.ndarray) -> Companions | None:
    """The companions of a dataset's controls (see the module doc), or None where the
    expression model has no face parts. expressions (N, E): its training frames'."""
    if not applies(kind, names, num_vertices) or len(expressions) < 2:
        return None
    parts = [part_and_side(n) for n in names]
    follows = np.zeros((len(names), len(names)), bool)
    for k, (pk, sk) in enumerate(parts):
        if pk in (None, "none"):
            continue
        for j, (pj, sj) in enumerate(parts):
            # an unsided control (jawOpen) carries both sides; a sided one its own side
            follows[k, j] = j != k and pj == pk and (not sk or sj == sk)
    return Companions(list(names), follows, np.asarray(expressions, np.float64))


def dataset_companions(ds) -> Companions | None:
    """`fit_companions` on a dataset's training frames."""
    return fit_companions(ds.expression_names, ds.expression_kind,
                          int(ds.face_vertices.shape[1]), training_expressions(ds))
