"""One line for the user (no traceback): what the panel's status and the operators' reports show."""
from __future__ import annotations

import re
from typing import Optional, Sequence

from . import torch_install

INSTALL_WHERE = "install it in Edit > Preferences > Add-ons > 4-LEGS Highlights (Install PyTorch)"
_BLENDER_PREFIX = re.compile(r"^(Error|Warning|Info):\s*")


def missing_line(names: Sequence[str]) -> str:
    """'torch is missing (what it is for); install it in ...' for missing modules ``names``."""
    return f"{torch_install.missing_message(list(names))}; {INSTALL_WHERE}"


def missing_for(names: Sequence[str] = ("torch",)) -> Optional[str]:
    """The one line naming what of ``names`` is missing here and where to install it, or None."""
    missing = torch_install.missing_modules(names)
    return missing_line(missing) if missing else None


def error_line(exc: BaseException) -> str:
    """The message of ``exc`` on one line; a missing dependency names what to install and where; the
    "Error: " Blender puts before an operator's report is not repeated."""
    if isinstance(exc, ModuleNotFoundError) and exc.name in torch_install.REQUIREMENTS:
        return missing_line([exc.name])
    text = str(exc) if isinstance(exc, (ValueError, FileExistsError, RuntimeError)) else f"{type(exc).__name__}: {exc}"
    text = " ".join(text.split())
    while _BLENDER_PREFIX.match(text):
        text = _BLENDER_PREFIX.sub("", text, count=1)
    return text
