"""`name=value[,name=value...]` as users type them (expression keyframes, head poses)."""

from __future__ import annotations

import difflib
import math

from flamenerf.errors import UserError


def suggest(name: str, names: list[str]) -> str:
    """'; did you mean X?' for the closest of `names`, or ''."""
    close = difflib.get_close_matches(name, names, n=1)
    return f"; did you mean {close[0]!r}?" if close else ""


def parse_assignments(item: str, names: list[str], where: str, kind: str = "name",
                      alternative: str = "") -> dict[str, float]:
    """`name=value[,...]` -> {name: finite float}, in the order given; a one-line UserError
    naming `where` and the item for anything else. `kind` names what the names are in the
    messages ("control"); `alternative` is appended to the malformed-item message (e.g. what
    else the option takes)."""
    out: dict[str, float] = {}
    for part in item.split(","):
        part = part.strip()
        if not part:
            continue
        if "=" not in part:
            raise UserError(f"{where} {item!r}: expected name=value, got {part!r}{alternative}")
        name, val = (s.strip() for s in part.split("=", 1))
        if name not in names:
            raise UserError(f"{where} {item!r}: unknown {kind} {name!r}{suggest(name, names)} "
                            f"(one of: {', '.join(names)})")
        try:
            v = float(val)
        except ValueError:
            raise UserError(f"{where} {item!r}: {val!r} is not a number") from None
        if not math.isfinite(v):
            raise UserError(f"{where} {item!r}: {name} must be finite")
        if name in out:
            raise UserError(f"{where} {item!r}: {name} is given twice")
        out[name] = v
    return out
