"""`name=value[,name=value...]` as users type them (expression keyframes, head poses), and
the controls a typed name means (`resolve_control`)."""

from __future__ import annotations

import difflib
import math

from flamenerf.errors import UserError


def suggest(name: str, names: list[str]) -> str:
    """'; did you mean X?' for the closest of `names`, or ''."""
    close = difflib.get_close_matches(name, names, n=1)
    return f"; did you mean {close[0]!r}?" if close else ""


def parse_assignments(item: str, names: list[str], where: str, kind: str = "name",
                      alternative: str = "", typed: str | None = None) -> dict[str, float]:
    """`name=value[,...]` -> {name: finite float}, in the order given; a one-line UserError
    naming `where` and the item for anything else. `kind` names what the names are in the
    messages ("control"); `alternative` is appended to the malformed-item message (e.g. what
    else the option takes); `typed`: the item as the user typed it, for the messages, where
    `item` is a rewriting of it."""
    out: dict[str, float] = {}
    shown = item if typed is None else typed
    for part in item.split(","):
        part = part.strip()
        if not part:
            continue
        if "=" not in part:
            raise UserError(f"{where} {shown!r}: expected name=value, got {part!r}{alternative}")
        name, val = (s.strip() for s in part.split("=", 1))
        if name not in names:
            raise UserError(f"{where} {shown!r}: unknown {kind} {name!r}{suggest(name, names)} "
                            f"(one of: {', '.join(names)})")
        try:
            v = float(val)
        except ValueError:
            raise UserError(f"{where} {shown!r}: {val!r} is not a number") from None
        if not math.isfinite(v):
            raise UserError(f"{where} {shown!r}: {name} must be finite")
        if name in out:
            raise UserError(f"{where} {shown!r}: {name} is given twice")
        out[name] = v
    return out


def resolve_control(name: str, names: list[str]) -> list[str] | None:
    """The controls `name` means where people type one (an edit, a keyframe): itself, the
    one of that name in another case, or both sides of a pair's stem (`mouthSmile`); None
    for none of these."""
    if name in names:
        return [name]
    folded = [n for n in names if n.lower() == name.lower()]
    if len(folded) == 1:
        return folded
    sides = [name + side for side in ("Left", "Right")]
    if all(n in names for n in sides):
        return sides
    return None
