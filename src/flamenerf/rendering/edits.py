"""Expression edits (`render --edit`): change some controls in every frame of a sequence and
leave the rest as the source has them.

The point is the filmed clip itself: `--split capture --edit mouthSmileLeft+=0.3,...`
renders the video as it was shot, with a broader smile throughout, and `--side-by-side`
puts each filmed frame beside its edit. Edits apply to any source (a driving video, a file).

An item is `name=V` (set to V), `name+=D` / `name-=D` (raise or lower by D) or `name*=S`
(scale by S: 0 removes the control's motion, 1.5 exaggerates it). `all` stands for every
control no other item names: `all*=1.5` exaggerates the whole expression, `all*=0,jawOpen*=1`
keeps only the jaw's motion. With companions
(data/companions.py) the controls the tracker reads with an edited one move by their
regression on its change, frame by frame, as for keyframes; and as for keyframes, the
edited controls are clamped to the range the training frames cover unless `--extrapolate`,
before their companions follow (rendering/videos.py; the viewer's Edit box alike).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from flamenerf.data.companions import Companions
from flamenerf.data.expression_range import ExpressionRange
from flamenerf.errors import UserError
from flamenerf.keyvalues import suggest
from flamenerf.rendering.expressions import MAX_ABS

OPS = ("+=", "-=", "*=", "=")
ALL = "all"  # every control no other item names
_ITEM = re.compile(r"^\s*(?P<name>[^=+*\s-][^=+*\s]*?)\s*(?P<op>\+=|-=|\*=|=)\s*(?P<amount>\S+)\s*$")


@dataclass(frozen=True)
class Edit:
    index: int  # the control's column in the run's order
    name: str
    op: str  # one of OPS
    amount: float

    def apply(self, v: np.ndarray) -> np.ndarray:
        """A control's values (T,) -> edited (T,)."""
        if self.op == "=":
            return np.full_like(v, self.amount)
        if self.op == "*=":
            return v * self.amount
        return v + (self.amount if self.op == "+=" else -self.amount)

    def __str__(self) -> str:
        return f"{self.name}{self.op}{self.amount:g}"


def parse_edits(items: list[str], names: list[str]) -> list[Edit]:
    """`--edit` values, each `name=V`, `name+=D`, `name-=D` or `name*=S`, comma-separated
    within an item -> edits in the order given; a one-line UserError for anything else."""
    index = {n: i for i, n in enumerate(names)}
    edits: list[Edit] = []
    every: tuple[str, float] | None = None  # `all`'s operation
    for item in items:
        for part in item.split(","):
            if not part.strip():
                continue
            m = _ITEM.match(part)
            if not m:
                raise UserError(f"--edit {item!r}: expected name=V, name+=D, name-=D or "
                                f"name*=S, got {part.strip()!r}")
            name, op = m["name"], m["op"]
            if name not in index and name != ALL:
                raise UserError(f"--edit {item!r}: unknown control {name!r}"
                                f"{suggest(name, names)} (one of: {', '.join(names)})")
            try:
                amount = float(m["amount"])
            except ValueError:
                raise UserError(f"--edit {item!r}: {m['amount']!r} is not a number") from None
            if not math.isfinite(amount) or abs(amount) > MAX_ABS:
                raise UserError(f"--edit {item!r}: {name}'s amount must be finite and at "
                                f"most {MAX_ABS:g} in size")
            if any(e.name == name for e in edits) or (name == ALL and every is not None):
                raise UserError(f"--edit: {name} is edited twice (one edit a control)")
            if name == ALL and name not in index:
                every = (op, amount)
            else:
                edits.append(Edit(index[name], name, op, amount))
    if every is not None:
        named = {e.name for e in edits}
        edits += [Edit(j, n, *every) for j, n in enumerate(names) if n not in named]
    if not edits:
        raise UserError("--edit: give at least one edit, e.g. mouthSmileLeft+=0.3")
    return edits


def apply_edits(values: np.ndarray, edits: list[Edit], companions: Companions | None = None,
                limits: ExpressionRange | None = None) -> tuple[np.ndarray, list[str], list[str]]:
    """Expressions (T, E) with `edits` applied to every frame: each edited control clamped
    to `limits` where given (the training range, unless the user asked to extrapolate),
    then with `companions` their companions moved by their regression on each frame's
    (clamped) change, within the training range. -> (edited (T, E), the names of the
    companions that moved, one line per edited control that was clamped
    (ExpressionRange.beyond))."""
    values = np.asarray(values, np.float32)
    new = {e.index: e.apply(values[:, e.index]) for e in edits}
    over: list[str] = []
    if limits is not None:
        asked = np.tile(limits.lo, (len(values), 1))  # the unedited controls: in range
        for k, v in new.items():
            asked[:, k] = v
        over = limits.beyond(asked)
        new = {k: np.clip(v, limits.lo[k], limits.hi[k]) for k, v in new.items()}
    if companions is None:
        out = values.copy()
        for k, v in new.items():
            out[:, k] = v
        return out, [], over
    out = companions.complete_frames(values, new).astype(np.float32)
    moved = np.any(np.abs(out - values) > 1e-6, axis=0)
    moved[list(new)] = False
    return out, [n for n, m in zip(companions.names, moved) if m], over
