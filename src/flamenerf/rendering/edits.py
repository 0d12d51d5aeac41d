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
from flamenerf.data.dataset_checks import MAX_CONTROL
from flamenerf.data.expression_range import ExpressionRange
from flamenerf.errors import UserError
from flamenerf.keyvalues import resolve_control, suggest
from flamenerf.rendering.expressions import ease

OPS = ("+=", "-=", "*=", "=")
ALL = "all"  # every control no other item names (not MediaPipe's `_neutral`)
# one edit: a name, an operator and an amount, with or without spaces between them; items
# are separated by commas or spaces (a shell splits `jawOpen += 0.3` into three words)
_ITEM = re.compile(r"(?P<name>[^\s,=+*-][^\s,=+*]*?)\s*(?P<op>\+=|-=|\*=|=)\s*"
                   r"(?P<amount>[^\s,]+)")


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
    """`--edit` values, each `name=V`, `name+=D`, `name-=D` or `name*=S`, separated by
    commas or spaces -> edits in the order given; a one-line UserError for anything else.
    A name is a control's (in any case), `all`, or a pair's stem (`mouthSmile` for
    mouthSmileLeft and mouthSmileRight)."""
    text = " ".join(items)
    edits: list[Edit] = []
    every: tuple[str, float] | None = None  # `all`'s operation
    rest = _ITEM.sub(" ", text).replace(",", " ").strip()
    if rest:
        raise UserError(f"--edit {text!r}: expected name=V, name+=D, name-=D or name*=S, "
                        f"got {rest.split()[0]!r}")
    for m in _ITEM.finditer(text):
        op = m["op"]
        if op == "=" and m["amount"].startswith("+"):  # `=+0.3`: a `+=` typed backwards
            raise UserError(f"--edit {m[0]!r}: sets {m['name']} to {m['amount'][1:]}; to "
                            f"raise it by that write {m['name']}+={m['amount'][1:]} (to set "
                            f"it, {m['name']}={m['amount'][1:]})")
        try:
            amount = float(m["amount"])
        except ValueError:
            raise UserError(f"--edit {m[0]!r}: {m['amount']!r} is not a number") from None
        if not math.isfinite(amount) or abs(amount) > MAX_CONTROL:
            raise UserError(f"--edit {m[0]!r}: the amount must be finite and at most "
                            f"{MAX_CONTROL:g} in size")
        if m["name"] == ALL and ALL not in names:
            if every is not None:
                raise UserError(f"--edit: {ALL} is edited twice (one edit a control)")
            every = (op, amount)
            continue
        for name in _controls(m["name"], names, m[0]):
            if any(e.name == name for e in edits):
                raise UserError(f"--edit: {name} is edited twice (one edit a control)")
            edits.append(Edit(names.index(name), name, op, amount))
    if every is not None:
        named = {e.name for e in edits}
        edits += [Edit(j, n, *every) for j, n in enumerate(names)
                  if n not in named and not n.startswith("_")]
    if not edits:
        raise UserError("--edit: give at least one edit, e.g. mouthSmileLeft+=0.3")
    return edits


def _controls(name: str, names: list[str], item: str) -> list[str]:
    """The controls an edit's `name` means (`resolve_control`); else a one-line UserError
    that suggests the nearest."""
    found = resolve_control(name, names)
    if found is not None:
        return found
    # what a name may be: a control, a pair's stem, `all`; a near spelling first, else
    # those that hold the word typed (`smile` -> mouthSmile)
    stems = sorted({n[:-4] for n in names if n.endswith("Left") and n[:-4] + "Right" in names})
    every = names + stems + [ALL]
    close = suggest(name, every)
    if not close:
        holding = [n for n in stems + names if name.lower() in n.lower()][:4]
        close = f"; did you mean {' or '.join(repr(n) for n in holding)}?" if holding else ""
    raise UserError(f"--edit {item!r}: unknown control {name!r}{close}" + (
        "" if close else f" (one of: {', '.join(names)}; a pair's stem for both sides: "
        f"{', '.join(stems) or 'none'}; or {ALL})"))


def describe(items: list[str]) -> str:
    """The edit as typed, tidied: `mouthSmile+=0.3, jawOpen*=0`."""
    return ", ".join(m[0].replace(" ", "") for m in _ITEM.finditer(" ".join(items)))


EASE_S = 0.3  # seconds an edit limited in time takes to come in and to go


@dataclass(frozen=True)
class EditWindow:
    """When an edit applies (`--edit-during START:END`, seconds of the video; either end
    may be left out): fully between them, eased in and out over `EASE_S` inside them."""

    start: float | None
    end: float | None

    @classmethod
    def parse(cls, text: str) -> "EditWindow":
        parts = text.split(":")
        if len(parts) != 2:
            raise UserError(f"--edit-during {text!r}: expected START:END in seconds (e.g. "
                            "2:4.5; 2: to the end, :3 from the start)")
        ends = []
        for p in parts:
            try:
                v = float(p) if p.strip() else None
            except ValueError:
                raise UserError(f"--edit-during {text!r}: {p!r} is not a number of "
                                "seconds") from None
            if v is not None and (not math.isfinite(v) or v < 0):
                raise UserError(f"--edit-during {text!r}: times are seconds from the "
                                "start, 0 or more")
            ends.append(v)
        if ends == [None, None]:
            raise UserError(f"--edit-during {text!r}: give a start, an end or both (without "
                            "--edit-during the edit applies to every frame)")
        if ends[0] is not None and ends[1] is not None and ends[1] <= ends[0]:
            raise UserError(f"--edit-during {text!r}: the end must come after the start")
        return cls(*ends)

    def weights(self, n: int, fps: float) -> np.ndarray:
        """How much of the edit each of n frames at `fps` shows (n,), in [0, 1]; a
        UserError when the window misses every frame."""
        t = np.arange(n) / fps
        lo = 0.0 if self.start is None else self.start
        hi = t[-1] + 1.0 / fps if self.end is None else self.end
        span = min(EASE_S, (hi - lo) / 2)
        w = np.ones(n)
        if self.start is not None and self.start > 0:
            w = np.minimum(w, (t - lo) / span if span > 0 else t >= lo)
        if self.end is not None:
            w = np.minimum(w, (hi - t) / span if span > 0 else t < hi)
        w = ease(w)
        if not w.any():
            length = n / fps
            raise UserError(f"--edit-during {self}: " + (
                f"the video is {length:.3g} s long" if lo >= length else
                f"no frame falls inside it once eased in and out (frames every "
                f"{1 / fps:.3g} s)"))
        return w.astype(np.float32)

    def __str__(self) -> str:
        return ":".join("" if v is None else f"{v:g}" for v in (self.start, self.end))

    def describe(self) -> str:
        """`3-6 s`, `8.5 s to the end`, `the start to 3 s`."""
        if self.start is not None and self.end is not None:
            return f"{self.start:g}-{self.end:g} s"
        a = "the start" if self.start is None else f"{self.start:g} s"
        return f"{a} to {'the end' if self.end is None else f'{self.end:g} s'}"

    def file_tag(self) -> str:
        """`2-4.5s`, `2s-end`, `start-3s`: the window in a file's name."""
        if self.start is not None and self.end is not None:
            return f"{self.start:g}-{self.end:g}s"
        return (f"{self.start:g}s-end" if self.start is not None
                else f"start-{self.end:g}s")


_FILE_OPS = {"+=": "+", "-=": "-", "*=": "x", "=": "="}  # `*` is a shell's wildcard


def file_tag(items: list[str], names: list[str], longest: int = 60) -> str:
    """The edit as a part of a file name, so that two edits of one clip get two videos:
    `mouthSmile+0.3_jawOpenx0` for `mouthSmile += .3, JAWOPEN*=0` (a control's own
    spelling, a stem or `all` as typed); `edited` where that would be longer than `longest`
    characters or hold a character a file name should not. `items` parse (`parse_edits`)."""
    by_case = {n.lower(): n for n in names}
    tag = "_".join(f"{by_case.get(m['name'].lower(), m['name'])}{_FILE_OPS[m['op']]}"
                   f"{float(m['amount']):g}" for m in _ITEM.finditer(" ".join(items)))
    if not tag or len(tag) > longest or not re.fullmatch(r"[\w.+=-]+", tag):
        return "edited"
    return tag


def apply_edits(values: np.ndarray, edits: list[Edit], companions: Companions | None = None,
                limits: ExpressionRange | None = None) -> tuple[np.ndarray, list[str], list[str]]:
    """Expressions (T, E) with `edits` applied to every frame: each edited control clamped
    to `limits` where given (the training range, unless the user asked to extrapolate),
    then with `companions` their companions moved by their regression on each frame's
    (clamped) change, within the training range. -> (edited (T, E), the names of the
    companions that moved, one line per edited control that was clamped, with the frames
    it was clamped in)."""
    values = np.asarray(values, np.float32)
    new = {e.index: e.apply(values[:, e.index]) for e in edits}
    over: list[str] = []
    if limits is not None:
        over = _clamped(new, limits)
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


def _clamped(new: dict[int, np.ndarray], limits: ExpressionRange, tol: float = 0.02,
             shown: int = 6) -> list[str]:
    """One line per edited control that leaves the range in some frames (by more than
    `tol`), saying in how many: an edit asks for a value per frame, and one side of a pair
    may be held back in every frame while the other never is."""
    lines = []
    for k, v in new.items():
        lo, hi = limits.lo[k], limits.hi[k]
        out = (v > hi + tol) | (v < lo - tol)
        if out.any():
            far = v[out][np.argmax(np.abs(v[out] - np.clip(v[out], lo, hi)))]
            lines.append(f"{limits.names[k]} in {int(out.sum())} of {len(v)} frames (asked "
                         f"{'up' if far > hi else 'down'} to {far:.2f}; the clip: "
                         f"{lo:.2f}-{hi:.2f})")
    if len(lines) > shown:
        lines = lines[:shown] + [f"and {len(lines) - shown} more controls"]
    return lines


@dataclass
class EditedSequence:
    """A sequence with an edit applied (`edit_sequence`)."""

    values: np.ndarray  # (T, E) the edited expressions
    changed: np.ndarray  # (T,) bool: the frames the edit changes
    tag: str  # the edit (and its window) in a file's name
    where: str  # "in every frame", or the window's frames, for a note
    moved: list[str]  # the companions that moved
    over: list[str]  # one line per edited control that was clamped (`_clamped`)


def edit_sequence(values: np.ndarray, edits: list[Edit], items: list[str], names: list[str],
                  companions: Companions | None, limits: ExpressionRange | None,
                  during: str | None, fps: float) -> EditedSequence:
    """Expressions (T, E) with `edits` (parsed from `items`, `parse_edits`) applied as
    `apply_edits` applies them, in every frame, or with `during` (`--edit-during`) inside
    its window only, eased in and out at its ends (the clamp and the companions are those
    of the window's frames) at `fps` frames per second."""
    values = np.asarray(values, np.float32)
    tag = file_tag(items, names)
    if during is None:
        out, moved, over = apply_edits(values, edits, companions, limits)
        return EditedSequence(out, np.ones(len(values), bool), tag, "in every frame",
                              moved, over)
    window = EditWindow.parse(during)
    w = window.weights(len(values), fps)
    inside = w > 0
    edited, moved, over = apply_edits(values[inside], edits, companions, limits)
    out = values.copy()
    out[inside] += w[inside, None] * (edited - values[inside])
    a, b = np.flatnonzero(inside)[[0, -1]]
    where = f"from frame {a} to {b} ({window.describe()}, eased in and out"
    if w.max() < 0.995:  # too short to ease in and out in full
        where += (f"; the window is too short for the whole edit, which reaches "
                  f"{100 * w.max():.0f} % of it at most")
    return EditedSequence(out, inside, f"{tag}_{window.file_tag()}", where + ")", moved, over)
