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


def memory_bytes() -> int | None:
    """The machine's physical memory in bytes (None where it cannot be read)."""
    import os

    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):
        return None


#: the share of physical memory one job may plan to use
MEMORY_SHARE = 0.8


def check_memory(nbytes: float, what: str, field: str) -> None:
    """InputError with the estimate when a job would need more than :data:`MEMORY_SHARE` of the machine's
    memory (checked before the work starts, so it is refused instead of killed by the OOM killer)."""
    total = memory_bytes()
    if total is not None and nbytes > MEMORY_SHARE * total:
        raise InputError(f"{what} needs about {format_bytes(nbytes)}, more than this machine's "
                         f"{format_bytes(total)} of memory allows; use smaller settings", field=field)


def format_bytes(nbytes: float) -> str:
    """1536 -> '1.5 KiB'."""
    value = float(nbytes)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if value < 1024 or unit == "PiB":
            return f"{value:.1f} {unit}" if unit != "B" else f"{int(value)} B"
        value /= 1024
    return f"{value:.1f} PiB"
