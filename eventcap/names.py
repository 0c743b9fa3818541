"""Messages about names a user gave that do not exist (a leaf module every layer may use)."""

from __future__ import annotations

import difflib


def unknown_name_message(what: str, name: str, available: list[str], where: str = "") -> str:
    """``no stage named 'eklT' (in ...); did you mean 'eklt'? Available: a, b, c``"""
    msg = f"no {what} named {name!r}" + (f" in {where}" if where else "")
    close = difflib.get_close_matches(name, available, n=3, cutoff=0.6)
    if not close:
        close = [a for a in available if a.lower() == str(name).lower()]
    if close:
        msg += "; did you mean " + " or ".join(repr(c) for c in close) + "?"
    msg += f" Available: {', '.join(available) if available else '(none installed)'}"
    return msg
