"""Error types shared by the whole engine.

Every problem with user input is raised as :class:`InputError`, which names the file, the field and
the problem, so the CLI can print one clear line instead of a traceback.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable, Optional


class FourlegsError(Exception):
    """Base class of every error the engine raises on purpose."""


class InputError(FourlegsError, ValueError):
    """Bad user input: names the file (if any), the field (if any) and the problem.

    >>> str(InputError("timestep 9 is out of range 0..4", file="a/scene.json", field="t"))
    'a/scene.json: t: timestep 9 is out of range 0..4'
    """

    def __init__(self, problem: str, *, file: str | Path | None = None, field: str | None = None):
        self.file = str(file) if file is not None else None
        self.field = field
        self.problem = problem
        parts = [p for p in (self.file, self.field) if p]
        super().__init__(": ".join(parts + [problem]))


class Cancelled(FourlegsError):
    """A long computation stopped because its progress callback asked it to (the user cancelled)."""


class ConfigMismatchError(FourlegsError):
    """Existing partial results were produced by a different configuration."""


class OutputExistsError(FourlegsError, FileExistsError):
    """An output already exists and overwriting was not requested."""

    def __init__(self, path: str | Path):
        self.path = str(path)
        super().__init__(f"{path}: already exists (pass --overwrite / overwrite=True to replace it)")


_ALLOCATION_FAILURES = ("can't allocate memory", "cannot allocate memory", "out of memory",
                        "not enough memory", "bad_alloc")


def describe_environment_error(exc: BaseException) -> str | None:
    """One line for a failure caused by the machine rather than by the code, or None for a bug.

    ``OSError`` (full or read-only disk, permissions, a path component that is a file) names the
    path and what to do; ``MemoryError`` and allocation failures reported as ``RuntimeError`` by
    torch say that memory ran out. Anything else returns None (it deserves its traceback).

    >>> import errno
    >>> describe_environment_error(OSError(errno.ENOSPC, "No space left on device", "out/a.json"))
    'no space left on device while writing out/a.json; free some space and run the same command again'
    """
    import errno

    if isinstance(exc, OSError):
        path = exc.filename if exc.filename is not None else None
        if exc.filename2 is not None:
            path = f"{exc.filename} -> {exc.filename2}"
        where = f" while writing {path}" if path else ""
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return (f"no space left on device{where}; free some space and run the same command again")
        reason = (exc.strerror or str(exc) or type(exc).__name__).rstrip(".")
        hint = {errno.EROFS: "choose a writable output location",
                errno.EACCES: "check the permissions or choose another location",
                errno.EPERM: "check the permissions or choose another location",
                errno.ENOTDIR: "a parent of this path is a file, not a folder",
                errno.EISDIR: "this path is a folder; give a file name",
                errno.ENAMETOOLONG: "use a shorter path"}.get(exc.errno)
        if exc.errno == errno.EEXIST and exc.filename is not None and Path(exc.filename).is_file():
            hint = "it is a file where a folder is needed"
        prefix = f"{path}: " if path else ""
        return f"{prefix}{reason[:1].lower() + reason[1:]}" + (f" ({hint})" if hint else "")
    if isinstance(exc, MemoryError):
        return ("out of memory" + (f" ({exc})" if str(exc) else "")
                + "; use smaller settings (resolution scale, timesteps, batch size) or a machine with more memory")
    if isinstance(exc, RuntimeError):
        text = str(exc)
        if any(k in text.lower() for k in _ALLOCATION_FAILURES):
            first = next((line.strip() for line in text.splitlines() if "alloc" in line.lower() or
                          "memory" in line.lower()), text.splitlines()[0] if text else "")
            return f"out of memory ({first[:200]}); use smaller settings or a machine with more memory"
    return None


def print_error(message: str) -> None:
    """``fourlegs: error: <message>`` on stderr; bytes that are not UTF-8 (in paths or text given on the
    command line) are shown as escapes instead of failing the print."""
    line = f"fourlegs: error: {message}".encode("utf-8", "backslashreplace").decode("utf-8")
    print(line, file=sys.stderr)


def exit_code_of(work: Callable[[], Optional[int]]) -> int:
    """Run a command's ``work`` and turn how it ends into the process's exit code, so every front end
    (``fourlegs``, the headless main job) reports failures alike:

    - its own return value (None: 0);
    - 2 for an error the engine raises on purpose (bad input, an existing output), printed as one line;
    - 130 for Ctrl-C (the stages resume on the next run);
    - 0 when stdout is a pipe whose reader left (``fourlegs ... | head``);
    - 1 for the machine's limits (full or read-only disk, no memory: :func:`describe_environment_error`).

    Anything else is a bug and keeps its traceback (re-raised).
    """
    try:
        return int(work() or 0)
    except FourlegsError as exc:
        print_error(str(exc))
        return 2
    except BrokenPipeError:
        sys.stderr.close()
        return 0
    except KeyboardInterrupt:
        print("fourlegs: cancelled; run the same command again to resume", file=sys.stderr)
        return 130
    except (OSError, MemoryError, RuntimeError) as exc:
        message = describe_environment_error(exc)
        if message is None:
            raise
        print_error(message)
        return 1
