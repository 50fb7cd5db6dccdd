"""Hostile values and JSON surgery shared by the robustness fuzz tests."""
from __future__ import annotations

from typing import Any, Iterator

from hypothesis import strategies as st

NOT_UTF8 = b"ball \xff\xfe".decode("utf-8", "surrogateescape")

#: a JSON value of the wrong type, out of range, not finite, a path outside its folder or nested too deeply
HOSTILE_JSON = st.one_of(
    st.none(), st.booleans(), st.sampled_from([0, -1, 1, 2, 10**10, 10**30, 2**63]),
    st.sampled_from([0.0, -1.0, 0.5, 1e30, -1e300, float("nan"), float("inf")]),
    st.sampled_from(["", "x", "/etc/hostname", "../../x.npy", "language/../../x", NOT_UTF8, "1e30"]),
    st.lists(st.integers(-3, 3), max_size=3), st.dictionaries(st.sampled_from(["a", "K", "w"]), st.integers(), max_size=2),
    st.just([[1, 2, 3], [4, 5, 6], [7, 8, 9]]))


def json_paths(obj: Any, prefix: tuple = ()) -> Iterator[tuple]:
    """Every (path to a value) of a JSON document, containers included (the first 3 items of a list)."""
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from json_paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj[:3]):
            yield from json_paths(v, prefix + (i,))


def replace_at(obj: Any, path: tuple, value: Any) -> Any:
    """``obj`` with the value at ``path`` replaced (in place; the new root is returned)."""
    if not path:
        return value
    obj[path[0]] = replace_at(obj[path[0]], path[1:], value)
    return obj


def remove_at(obj: Any, path: tuple) -> Any:
    """``obj`` without the value at ``path`` (a dict key or a list item; the root itself is left alone)."""
    if path:
        parent = obj
        for key in path[:-1]:
            parent = parent[key]
        del parent[path[-1]]
    return obj


def run_command(argv: list[str], capsys) -> tuple[object, str]:
    """``fourlegs ARGV`` in this process on one torch thread: (exit code, what it wrote to stderr)."""
    import torch

    from fourlegs_engine.commands.main import main

    old = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        try:
            code = main(argv)
        except SystemExit as exc:
            code = exc.code
    finally:
        torch.set_num_threads(old)
    return code, capsys.readouterr().err
