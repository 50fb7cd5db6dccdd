"""One line for the user from an exception (no traceback): what the panel's status and reports show."""
from __future__ import annotations

from . import torch_install


def error_line(exc: BaseException) -> str:
    """The message of ``exc`` on one line; a missing dependency names what to install and where."""
    if isinstance(exc, ModuleNotFoundError) and exc.name in torch_install.REQUIREMENTS:
        return (f"{torch_install.missing_message([exc.name])}; install it in Edit > Preferences > Add-ons > "
                "4-LEGS Highlights")
    text = str(exc) if isinstance(exc, (ValueError, FileExistsError, RuntimeError)) else f"{type(exc).__name__}: {exc}"
    return " ".join(text.split())
