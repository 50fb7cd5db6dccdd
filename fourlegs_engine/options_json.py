"""Option dataclasses as JSON: how options cross a process boundary (the main job's Blender child) as data.

:func:`options_to_dict` gives plain JSON values (paths as strings, tuples as lists, nested option
dataclasses as objects); :func:`options_from_dict` builds the dataclass back, checking every value
against the field's annotation, so a malformed file fails with one line naming the file and the field::

    options_from_dict(HighlightJobOptions, json.loads(text), file="options.json")
"""
from __future__ import annotations

import math
import types
import typing
from dataclasses import fields, is_dataclass
from pathlib import Path
from typing import Any, Optional, TypeVar, Union

from .errors import InputError
from .validate import check_text

T = TypeVar("T")


def options_to_dict(options: Any) -> dict[str, Any]:
    """The fields of the dataclass ``options`` as JSON values."""
    return {f.name: _plain(getattr(options, f.name)) for f in fields(options)}


def _plain(value: Any) -> Any:
    if is_dataclass(value) and not isinstance(value, type):
        return options_to_dict(value)
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    return value


def options_from_dict(cls: type[T], data: Any, *, file: Optional[str | Path] = None, prefix: str = "") -> T:
    """``cls`` (a dataclass) from :func:`options_to_dict`'s output; missing fields keep their defaults.

    InputError (naming ``file`` and the field) for an unknown field or a value of the wrong type.
    """
    if not isinstance(data, dict):
        raise InputError(f"expected an object of {cls.__name__} fields, got {type(data).__name__}", file=file,
                         field=prefix.rstrip(".") or None)
    hints = typing.get_type_hints(cls)
    known = [f.name for f in fields(cls) if f.init]
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise InputError(f"unknown field(s) {', '.join(map(repr, unknown))} (known: {', '.join(known)})",
                         file=file, field=prefix.rstrip(".") or None)
    return cls(**{name: _typed(hints[name], value, file, prefix + name) for name, value in data.items()})


def _typed(annotation: Any, value: Any, file: Optional[str | Path], field: str) -> Any:
    """``value`` as ``annotation`` says (str, bool, int, float, Path, Optional/unions, tuples, dataclasses)."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin in (Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        first_problem = None
        for member in (a for a in args if a is not type(None)):
            try:
                return _typed(member, value, file, field)
            except InputError as exc:
                first_problem = first_problem or exc
        raise first_problem
    if is_dataclass(annotation):
        return options_from_dict(annotation, value, file=file, prefix=field + ".")
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise InputError(f"expected a list, got {value!r}", file=file, field=field)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_typed(args[0], v, file, f"{field}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise InputError(f"expected {len(args)} values, got {len(value)}", file=file, field=field)
        return tuple(_typed(a, v, file, f"{field}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    if annotation is Any:
        return value
    if annotation is str or annotation is Path:
        if not isinstance(value, str):
            raise InputError(f"expected text, got {value!r}", file=file, field=field)
        check_text(value, field)
        return value if annotation is str else Path(value)
    if annotation is bool:
        if not isinstance(value, bool):
            raise InputError(f"expected true or false, got {value!r}", file=file, field=field)
        return value
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(f"expected an integer, got {value!r}", file=file, field=field)
        return value
    if annotation is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise InputError(f"expected a finite number, got {value!r}", file=file, field=field)
        return float(value)
    raise TypeError(f"{field}: options_from_dict cannot read a {annotation!r} field")

