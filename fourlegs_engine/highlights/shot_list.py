"""Which shots a highlight gets: the preset's shots, its framed block repeated per subject and its
replays repeated per segment.

- Subjects: the framed shots (those that need the action centre: zoom-in, bullet time) form a block;
  with ``subjects = N`` in the preset the block is repeated for each of the first N instances the query
  matches (best first, :mod:`.instances`), each framing its own instance (the shot's ``subject``
  parameter: the instance's rank).
- Segments: with ``segments = "all"`` every replay shot (the masked effects, desaturate or blur the
  background) is repeated once per positive segment, in time order; with ``"picked"`` (the default) it
  replays the picked segment only.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Optional, Sequence

from .effects import MASKED_EFFECTS, NEED_ACTION_CENTRE, get_effect
from .framing import Framing
from .presets import Preset, ShotSpec

SEGMENT_MODES = ("picked", "all")


@dataclass
class PlannedShot:
    """A preset shot as built for this plan: its spec (name made unique) and what it overrides in the
    shot context (``framing`` and ``action_centre`` of its subject, ``segment`` and ``peak`` of its replay)."""

    spec: ShotSpec
    overrides: dict[str, Any] = field(default_factory=dict)


def _segment_peak(segment: tuple[int, int]) -> int:
    return (int(segment[0]) + int(segment[1])) // 2


def highlighted_segments(found, preset: Preset) -> list[tuple[int, int]]:
    """The segments the replays show: the picked one, or (``segments = "all"``) every positive segment in
    time order. ``found`` has ``segment`` and ``temporal.segments``."""
    if found.segment is None:
        return []
    if preset.segments != "all" or found.temporal is None:
        return [tuple(found.segment)]
    every = sorted({(int(a), int(b)) for a, b in (found.temporal.segments or [])} | {tuple(found.segment)})
    return every


def expand_shots(specs: Sequence[ShotSpec], subjects: Sequence[Optional[Framing]],
                 segments: Sequence[tuple[int, int]], *, subject_t: int = 0,
                 segment_framing: Optional[Callable[[int], Optional[Framing]]] = None) -> list[PlannedShot]:
    """The preset's shots with the framed block once per subject and each replay once per segment.

    Framed shots carry ``subject`` (the instance's rank) and ``subject_t`` (the timestep it was found at);
    a replay of another segment than the picked one follows the subject found at that segment's peak
    (``segment_framing(peak)``): the Gaussians that show a moving thing at one moment need not be the
    ones that show it at another.

    Args:
        specs: the preset's shots that can be built (needs met), in order.
        subjects: the framing of each subject, best first (``[None]`` without framing).
        segments: the segments to replay, the picked one among them.
        subject_t: the timestep the subjects were found at (the peak).
        segment_framing: the subject's framing at a timestep (None: replays keep the picked subject).
    """
    framed = [i for i, s in enumerate(specs) if NEED_ACTION_CENTRE in get_effect(s.effect).needs(s.params, first=False)]
    subjects = [f for f in subjects if f is not None] or [None]
    out: list[PlannedShot] = []
    for i, spec in enumerate(specs):
        if framed and i == framed[0]:
            block = specs[framed[0]:framed[-1] + 1]
            for k, framing in enumerate(subjects):
                for s in block:
                    name = s.name if k == 0 else f"{s.name} {k + 1}"
                    over = {} if framing is None or k == 0 else {"framing": framing, "action_centre": framing.centre}
                    out.append(PlannedShot(ShotSpec(name, s.effect, {**s.params, "subject": k,
                                                                     "subject_t": int(subject_t)}), over))
            continue
        if framed and framed[0] < i <= framed[-1]:
            continue
        if spec.effect in MASKED_EFFECTS and len(segments) > 1:
            for seg in segments:
                name = f"{spec.name} {seg[0]}-{seg[1]}"
                peak = _segment_peak(seg)
                over: dict[str, Any] = {"segment": tuple(seg), "peak": peak}
                framing = None if segment_framing is None or peak == subject_t else segment_framing(peak)
                if framing is not None:
                    over.update(framing=framing, action_centre=framing.centre)
                out.append(PlannedShot(ShotSpec(name, spec.effect, {**spec.params, "subject": 0,
                                                                    "subject_t": peak if framing else int(subject_t)}),
                                       over))
            continue
        out.append(PlannedShot(spec))
    return out
