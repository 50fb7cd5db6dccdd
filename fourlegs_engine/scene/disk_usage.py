"""What a scene bundle takes on disk, by part (``fourlegs info``)."""
from __future__ import annotations

import os
from pathlib import Path

#: the bundle's top-level files (geometry, colours, scene.json) are counted as this part
GEOMETRY = "geometry"


def bundle_disk_usage(root: str | Path) -> dict[str, int]:
    """Bytes allocated on disk under ``root`` (``st_blocks``: holes of sparse files are free, a file with
    several hard links inside the bundle counts once), by part: each sub-directory by its name
    (``features``, ``language``, ``query``, ...) and the top-level files as ``geometry``; plus ``total``."""
    root = Path(root)
    parts: dict[str, int] = {}
    seen: set[tuple[int, int]] = set()
    for directory, _, files in os.walk(root):
        rel = Path(directory).relative_to(root).parts
        part = rel[0] if rel else GEOMETRY
        for name in files:
            try:
                st = os.lstat(os.path.join(directory, name))
            except OSError:  # removed while walking (a stage finishing next to us)
                continue
            if (st.st_dev, st.st_ino) in seen:
                continue
            seen.add((st.st_dev, st.st_ino))
            parts[part] = parts.get(part, 0) + int(getattr(st, "st_blocks", 0)) * 512
    parts["total"] = sum(parts.values())
    return parts
