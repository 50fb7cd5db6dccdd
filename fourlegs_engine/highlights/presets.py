"""Highlight presets: TOML files describing the output format and the sequence of shots.

A preset file::

    name = "broadcast"                    # defaults to the file name
    description = "context, zoom-in, bullet-time, desaturated replay"
    fps = 24                              # output frame rate
    resolution = [1280, 720]              # output width, height
    fov_fit = "vertical"                  # keep the best view's vertical (or horizontal) field of view
    recentre = true                       # turn the best view so the action centre is mid-frame (§6.1)
    frame_start = 1
    sensor_width_mm = 36.0
    subjects = 1                          # the framed shots are repeated for each of the first N instances
    segments = "picked"                   # "all": one replay per positive segment

    [[shots]]
    name = "context"
    effect = "play"                       # play | zoom_in | bullet_time | desaturate_background | blur_background
    from = "segment_start"                # + any parameter of the effect (see effects.py)
    from_offset_s = -1.5

Where presets are found, first match wins: the directories given explicitly (``--preset-dir``),
then ``$FOURLEGS_PRESETS`` (os.pathsep-separated directories), then the repository's ``presets/``,
then a copy shipped inside the package (``fourlegs_engine/highlights/presets/``, used by the
Blender extension). A preset name may also be the path of a ``.toml`` file.
"""
from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Iterable, Optional, Sequence

from ..errors import InputError
from .effects import EFFECTS, get_effect

ENV_PRESETS = "FOURLEGS_PRESETS"
#: output bounds of a preset (and of the overrides of ``plan``/``highlight``): frames per second, pixels a side
MAX_FPS = 240
MIN_SIDE, MAX_SIDE = 16, 16384
_PACKAGE_DIR = Path(__file__).resolve().parent
REPO_PRESETS = _PACKAGE_DIR.parents[1] / "presets"
PACKAGED_PRESETS = _PACKAGE_DIR / "presets"
_TOP_KEYS = {"name", "description", "fps", "resolution", "fov_fit", "recentre", "frame_start",
             "sensor_width_mm", "subjects", "segments", "shots"}
#: How many of the instances a query matches get their own framed shots, at most.
MAX_SUBJECTS = 8


@dataclass
class ShotSpec:
    """One shot of a preset: its label, effect and fully resolved parameters."""

    name: str
    effect: str
    params: dict[str, Any]


@dataclass
class Preset:
    """A validated preset."""

    name: str
    description: str
    fps: float
    resolution: tuple[int, int]
    shots: list[ShotSpec]
    fov_fit: str = "vertical"
    recentre: bool = True
    frame_start: int = 1
    sensor_width_mm: float = 36.0
    source: Optional[str] = None
    subjects: int = 1
    segments: str = "picked"

    def select_effects(self, keep: Sequence[str] = (), drop: Sequence[str] = ()) -> "Preset":
        """A copy with only the shots whose effect is in ``keep`` (every effect when empty) and not in
        ``drop``. InputError for an unknown effect name, or for a ``keep`` that no shot of the preset has."""
        for field, names in (("effects", keep), ("no_effect", drop)):
            unknown = [e for e in names if e not in EFFECTS]
            if unknown:
                raise InputError(f"unknown effects {unknown} (one of {', '.join(EFFECTS)})", field=field)
        if keep and not any(s.effect in keep for s in self.shots):
            raise InputError(f"preset {self.name!r} has no shot with the effects {list(keep)}", field="effects")
        return self.with_shots([s.effect for s in self.shots if (not keep or s.effect in keep) and s.effect not in drop])

    def with_shots(self, effects: Iterable[str]) -> "Preset":
        """A copy keeping only the shots whose effect is in ``effects``."""
        keep = set(effects)
        return replace(self, shots=[s for s in self.shots if s.effect in keep])


def search_dirs(extra: Sequence[str | Path] = ()) -> list[Path]:
    """Preset directories in lookup order (existing ones only, no duplicates)."""
    env = [p for p in os.environ.get(ENV_PRESETS, "").split(os.pathsep) if p]
    out: list[Path] = []
    for d in [*map(Path, extra), *map(Path, env), REPO_PRESETS, PACKAGED_PRESETS]:
        d = d.expanduser()
        if d.is_dir() and d.resolve() not in [o.resolve() for o in out]:
            out.append(d)
    return out


def available_presets(extra: Sequence[str | Path] = ()) -> dict[str, Path]:
    """Preset name -> file, the first directory in lookup order winning."""
    found: dict[str, Path] = {}
    for d in search_dirs(extra):
        for f in sorted(d.glob("*.toml")):
            found.setdefault(f.stem, f)
    return found


def find_preset(name: str, extra: Sequence[str | Path] = ()) -> Path:
    path = Path(name).expanduser()
    if path.suffix == ".toml" or os.sep in name:
        if not path.is_file():
            raise InputError("preset file is missing", file=path, field="preset")
        return path
    presets = available_presets(extra)
    if name not in presets:
        where = ", ".join(str(d) for d in search_dirs(extra)) or "no preset directory found"
        raise InputError(f"unknown preset {name!r}; available: {', '.join(sorted(presets)) or 'none'} "
                         f"(searched {where})", field="preset")
    return presets[name]


def load_preset(name_or_path: str | Path, extra_dirs: Sequence[str | Path] = ()) -> Preset:
    """Find and validate a preset; problems raise :class:`InputError` naming file and field."""
    path = find_preset(str(name_or_path), extra_dirs)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML ({exc})", file=path) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot be read ({exc})", file=path) from None
    return parse_preset(data, file=path, default_name=path.stem)


def parse_preset(data: dict[str, Any], *, file: Any = None, default_name: str = "preset") -> Preset:
    """Validate a preset dictionary (as read from TOML)."""
    def bad(problem: str, where: str) -> InputError:
        return InputError(problem, file=file, field=where)

    for key in data:
        if key not in _TOP_KEYS:
            raise bad(f"unknown key (known: {', '.join(sorted(_TOP_KEYS))})", key)
    name = data.get("name", default_name)
    if not isinstance(name, str) or not name:
        raise bad("must be a non-empty string", "name")
    description = data.get("description", "")
    if not isinstance(description, str):
        raise bad("must be a string", "description")
    fps = data.get("fps", 24)
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not math.isfinite(fps) or not 1 <= fps <= 240:
        raise bad(f"must be a number of frames per second in 1..240, got {fps!r}", "fps")
    res = data.get("resolution", [1280, 720])
    if (not isinstance(res, list) or len(res) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and 16 <= v <= 16384 for v in res)):
        raise bad(f"must be [width, height] in pixels (whole numbers 16..16384), got {res!r}", "resolution")
    fov_fit = data.get("fov_fit", "vertical")
    if fov_fit not in ("vertical", "horizontal"):
        raise bad(f"must be 'vertical' or 'horizontal', got {fov_fit!r}", "fov_fit")
    recentre = data.get("recentre", True)
    if not isinstance(recentre, bool):
        raise bad(f"must be true or false, got {recentre!r}", "recentre")
    frame_start = data.get("frame_start", 1)
    if isinstance(frame_start, bool) or not isinstance(frame_start, int) or frame_start < 0:
        raise bad(f"must be a whole number >= 0, got {frame_start!r}", "frame_start")
    sensor = data.get("sensor_width_mm", 36.0)
    if isinstance(sensor, bool) or not isinstance(sensor, (int, float)) or not 1.0 <= sensor <= 200.0:
        raise bad(f"must be a sensor width in millimetres (1..200), got {sensor!r}", "sensor_width_mm")
    subjects = data.get("subjects", 1)
    if isinstance(subjects, bool) or not isinstance(subjects, int) or not 1 <= subjects <= MAX_SUBJECTS:
        raise bad(f"must be a whole number of subjects 1..{MAX_SUBJECTS}, got {subjects!r}", "subjects")
    segments = data.get("segments", "picked")
    if segments not in ("picked", "all"):
        raise bad(f"must be 'picked' or 'all', got {segments!r}", "segments")
    raw_shots = data.get("shots")
    if not isinstance(raw_shots, list) or not raw_shots:
        raise bad("needs at least one [[shots]] table", "shots")
    shots: list[ShotSpec] = []
    for i, raw in enumerate(raw_shots):
        where = f"shots[{i}]"
        if not isinstance(raw, dict):
            raise bad("must be a table", where)
        if "effect" not in raw:
            raise bad(f"missing 'effect' (one of {', '.join(EFFECTS)})", f"{where}.effect")
        effect = get_effect(raw["effect"] if isinstance(raw["effect"], str) else repr(raw["effect"]),
                            file=file, field=f"{where}.effect")
        label = raw.get("name", effect.name)
        if not isinstance(label, str) or not label:
            raise bad("must be a non-empty string", f"{where}.name")
        if label in [s.name for s in shots]:
            raise bad(f"duplicate shot name {label!r}", f"{where}.name")
        shots.append(ShotSpec(label, effect.name, effect.resolve(raw, where, file)))
    return Preset(name=name, description=description, fps=float(fps), resolution=(res[0], res[1]),
                  shots=shots, fov_fit=fov_fit, recentre=recentre, frame_start=frame_start,
                  sensor_width_mm=float(sensor), source=None if file is None else str(file), subjects=subjects,
                  segments=segments)
