"""Error types shared by the whole engine.

Every problem with user input is raised as :class:`InputError`, which names the file, the field and
the problem, so the CLI can print one clear line instead of a traceback.
"""
from __future__ import annotations

from pathlib import Path


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


class ConfigMismatchError(FourlegsError):
    """Existing partial results were produced by a different configuration."""


class OutputExistsError(FourlegsError, FileExistsError):
    """An output already exists and overwriting was not requested."""

    def __init__(self, path: str | Path):
        self.path = str(path)
        super().__init__(f"{path}: already exists (pass --overwrite / overwrite=True to replace it)")
