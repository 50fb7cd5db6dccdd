"""PyTorch for the add-on: where it goes, whether it is there, and a background pip install of it.

The extension does not bundle torch (see ``build.py``). Importing a scene and playing it on the
timeline work without it; querying, preparing a language field and rendering need it. The add-on's
preferences install it with Blender's own Python (``python -m pip install --target``) into the
extension's user directory (``bpy.utils.extension_path_user(package, path="site-packages")``), which
the add-on puts on ``sys.path`` when it registers, so nothing outside the extension is touched.

The pip run is a subprocess read by a worker thread; the preferences' modal operator polls
:class:`InstallJob` on a timer (progress, last line, outcome) and cancels it on Esc.
"""
from __future__ import annotations

import importlib
import importlib.util
import re
import subprocess
import sys
import threading
from pathlib import Path
from typing import Optional, Sequence

#: choice in the preferences -> (label, extra pip arguments)
VARIANTS = {
    "CPU": ("CPU (about 200 MB)", ["--index-url", "https://download.pytorch.org/whl/cpu"]),
    "CUDA": ("NVIDIA CUDA 12.8 (about 3 GB)", ["--index-url", "https://download.pytorch.org/whl/cu128"]),
}
#: what the add-on imports, with what it is needed for (shown by the panel when missing)
REQUIREMENTS = {
    "torch": "querying, preparing a language field and rendering",
    "scipy": "querying and planning highlights",
    "plyfile": "importing PLY scenes",
    "tqdm": "progress of long jobs",
}


def site_packages(package: str, create: bool = True) -> Path:
    """The extension's own site-packages (``extension_path_user``); outside the extension system (the
    add-on installed as a plain package) a ``fourlegs/site-packages`` folder in Blender's user scripts."""
    import bpy

    try:
        return Path(bpy.utils.extension_path_user(package, path="site-packages", create=create))
    except (ValueError, KeyError):
        return Path(bpy.utils.user_resource("SCRIPTS", path="fourlegs/site-packages", create=create))


def add_to_sys_path(path: Path) -> None:
    """Make packages installed at ``path`` importable in this Blender session."""
    if str(path) not in sys.path:
        sys.path.append(str(path))
    importlib.invalidate_caches()


def missing_modules(names: Sequence[str] = tuple(REQUIREMENTS)) -> list[str]:
    """The modules of ``names`` that cannot be imported here (found without importing them)."""
    out = []
    for name in names:
        try:
            if importlib.util.find_spec(name) is None:
                out.append(name)
        except (ImportError, ValueError):  # sys.modules[name] is None: made unimportable on purpose
            out.append(name)
    return out


def missing_message(names: Sequence[str]) -> str:
    """One line naming what is missing and what it is needed for."""
    return "; ".join(f"{name} is missing ({REQUIREMENTS.get(name, 'needed')})" for name in names)


def pip_install_command(target: Path, variant: str = "CPU", requirement: str = "torch",
                        extra_args: Sequence[str] = ()) -> list[str]:
    """``python -m pip install`` of ``requirement`` into ``target`` with the variant's package index."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown PyTorch build {variant!r}; choose one of {', '.join(VARIANTS)}")
    return [sys.executable, "-m", "pip", "install", "--upgrade", "--target", str(target), "--progress-bar", "off",
            "--no-input", "--disable-pip-version-check", *VARIANTS[variant][1], *extra_args, requirement]


# pip output line -> progress reached when it appears (pip prints these stages in order)
_STAGES = ((re.compile(r"^(Looking in|Processing|Collecting)"), 0.1, "resolving"),
           (re.compile(r"^\s*Downloading"), 0.3, "downloading"),
           (re.compile(r"^Installing collected packages"), 0.8, "installing"),
           (re.compile(r"^Successfully installed"), 1.0, "installed"))


class InstallJob:
    """One pip run in the background: ``progress`` in [0,1], ``stage``, ``last_line``, then ``done`` with
    ``ok`` and ``message``. ``cancel()`` stops pip (the target keeps what pip finished)."""

    def __init__(self, command: Sequence[str], target: Path):
        self.command, self.target = list(command), Path(target)
        self.progress, self.stage, self.last_line = 0.0, "starting pip", ""
        self.done, self.ok, self.cancelled = False, False, False
        self.message = ""
        self._process: Optional[subprocess.Popen] = None
        self._lines: list[str] = []
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> "InstallJob":
        self.target.mkdir(parents=True, exist_ok=True)
        self._thread.start()
        return self

    def wait(self, timeout: Optional[float] = None) -> bool:
        self._thread.join(timeout)
        return self.done

    def cancel(self) -> None:
        self.cancelled = True
        if self._process is not None and self._process.poll() is None:
            self._process.terminate()

    def _run(self) -> None:
        try:
            self._process = subprocess.Popen(self.command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                             text=True, bufsize=1)
            for line in self._process.stdout:
                line = line.rstrip()
                if not line or line.startswith("WARNING: Location"):
                    continue
                self._lines.append(line)
                self.last_line = line[:200]
                for pattern, progress, stage in _STAGES:
                    if pattern.search(line):
                        self.progress, self.stage = max(self.progress, progress), stage
            code = self._process.wait()
            if self.cancelled:
                self.message = "cancelled"
            elif code == 0:
                self.ok, self.progress, self.stage = True, 1.0, "installed"
                self.message = f"installed into {self.target}"
            else:
                errors = [l for l in self._lines if l.startswith("ERROR")] or self._lines[-1:] or [f"exit {code}"]
                self.message = f"pip failed: {errors[-1]}"
        except OSError as exc:
            self.message = f"pip could not start: {exc}"
        finally:
            self.done = True
