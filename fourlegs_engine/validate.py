"""Checks of user-given values made before any work starts: bounded numeric arguments and text.

Every check raises :class:`~fourlegs_engine.errors.InputError` with one line naming the argument and
the accepted range, so a bad value never reaches an allocation or a half-written output.
"""
from __future__ import annotations

import math
import numbers

from .errors import InputError


def check_text(text: str, field: str) -> str:
    """``text`` if it is valid Unicode that UTF-8 can encode; else :class:`InputError`.

    Command-line bytes that are not UTF-8 arrive as lone surrogates (``'\\udcff'``); JSON files
    accept them but plots, EXR headers and Blender do not, so they are refused before any output.

    >>> check_text("a ball", "text")
    'a ball'
    """
    if not isinstance(text, str):
        raise InputError(f"must be text, got {type(text).__name__}", field=field)
    try:
        text.encode("utf-8")
    except UnicodeEncodeError as exc:
        bad = text[exc.start]
        byte = ord(bad) - 0xDC00 if 0xDC80 <= ord(bad) <= 0xDCFF else None
        what = f"byte 0x{byte:02x}" if byte is not None else f"character U+{ord(bad):04X}"
        raise InputError(f"is not valid UTF-8 text ({what} at position {exc.start}); re-type it or set a "
                         "UTF-8 locale (e.g. LANG=C.UTF-8)", field=field) from None
    return text


def check_number(value: float, field: str, *, low: float | None = None, high: float | None = None,
                 low_open: bool = False, integer: bool = False) -> float:
    """``value`` if finite and within [low, high] (``low_open``: (low, high]); else :class:`InputError`."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
    if ok and integer and float(value) != int(value):
        ok = False
    if ok and low is not None and (value <= low if low_open else value < low):
        ok = False
    if ok and high is not None and value > high:
        ok = False
    if not ok:
        raise InputError(f"must be {'an integer' if integer else 'a finite number'}"
                         f"{_range_text(low, high, low_open)}, got {value!r}", field=field)
    return value


def _range_text(low: float | None, high: float | None, low_open: bool) -> str:
    if low is None and high is None:
        return ""
    if high is None:
        return f" {'>' if low_open else '>='} {low:g}"
    if low is None:
        return f" <= {high:g}"
    return f" in {'(' if low_open else '['}{low:g}, {high:g}]"
