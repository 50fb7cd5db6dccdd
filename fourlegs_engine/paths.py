"""Where generated artefacts (the demo scene, caches) live."""
from __future__ import annotations

import os
from pathlib import Path


def cache_dir() -> Path:
    """``$FOURLEGS_CACHE`` if set, else ``~/.cache/fourlegs``; created on demand."""
    root = Path(os.environ.get("FOURLEGS_CACHE") or Path.home() / ".cache" / "fourlegs")
    root.mkdir(parents=True, exist_ok=True)
    return root
