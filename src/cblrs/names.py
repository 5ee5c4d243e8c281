"""The names a person gives things in a site file (sites, planes, cameras, zones, lines,
calibration points): what they may contain.

A name is shown on the dashboard, written into tables, plots and file names, and sent on
the wire, so it is a short line of words: letters and digits of any script, spaces and a
few punctuation marks (:data:`NAME_PUNCTUATION`), at most :data:`NAME_MAX` characters, no
leading or trailing space. Markup (``<``, ``>``, ``&``, quotes), control characters and
invisible formatting characters are refused, so that ``cblrs site check`` flags a name such
as ``<img src=x onerror=...>`` before anything shows it. (The dashboard never relies on this:
it writes every name into the page as text.)
"""

from __future__ import annotations

import unicodedata

NAME_MAX = 64
NAME_PUNCTUATION = " _-.,:;()[]/+#@'"
"""The characters a name may hold besides letters, marks and digits."""


def name_problem(name: object) -> str | None:
    """Why ``name`` is not a good name (a phrase to complete "name ... "), or None when it is.

    Examples:
        >>> name_problem("north_gate") is None
        True
        >>> name_problem("<b>x</b>")
        "may not contain '<' (letters, digits, spaces and _-.,:;()[]/+#@' only)"
    """
    if not isinstance(name, str):
        return f"must be text, not {type(name).__name__}"
    if not name:
        return "must not be empty"
    if len(name) > NAME_MAX:
        return f"is {len(name)} characters long; at most {NAME_MAX}"
    if name != name.strip():
        return "must not start or end with a space"
    for character in name:
        if character in NAME_PUNCTUATION:
            continue
        if unicodedata.category(character)[0] in "LMN":
            continue
        shown = repr(character) if character.isprintable() else f"U+{ord(character):04X}"
        allowed = NAME_PUNCTUATION.strip()
        return f"may not contain {shown} (letters, digits, spaces and {allowed} only)"
    return None


def check_name(name: object, what: str) -> str:
    """``name`` when it is a good name, else ``ValueError`` saying why (``what``: "zone name")."""
    problem = name_problem(name)
    if problem is not None:
        raise ValueError(f"{what} {name!r} {problem}")
    assert isinstance(name, str)
    return name
