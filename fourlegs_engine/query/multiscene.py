"""Localization within several scenes (paper §6.2).

A scene's relevance to a query is ``max_t s_t``, computed on every k-th timestep (k = 10 in the paper)
to save time; the best scene is then localized in full. Note s_t is normalized over the sampled
timesteps, so scenes of different lengths are compared as the paper does (no extra correction).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Mapping, Optional

from ..errors import InputError
from .results import Localization

DEFAULT_SCENE_STRIDE = 10


@dataclass
class SceneRanking:
    """Scenes ranked by relevance (best first): ``[(name, max_t s_t)]``, plus the best scene's answer."""

    ranking: list[tuple[str, float]]
    best: Optional[str]
    localization: Optional[Localization]

    def to_dict(self) -> dict:
        return {"ranking": [[n, float(s)] for n, s in self.ranking], "best": self.best,
                "localization": None if self.localization is None else self.localization.to_dict()}


def scene_relevance(engine, query: str, stride: int = DEFAULT_SCENE_STRIDE) -> float:
    """``max_t s_t`` of ``query`` on every ``stride``-th timestep of the engine's scene (0 if not found)."""
    res = engine.temporal(query, stride=stride)
    sampled = res.scores[res.timesteps] if res.timesteps is not None and len(res.timesteps) else res.scores
    total = float(sampled.sum())
    # s_t normalized over the sampled timesteps, as in the paper
    return float(sampled.max() / total) if res.found and total > 0 else 0.0


def rank_scenes(engines: Mapping[str, object], query: str, *, stride: int = DEFAULT_SCENE_STRIDE,
                need: Iterable[str] = ("temporal",)) -> SceneRanking:
    """Rank ``engines`` ({scene name: QueryEngine}) by relevance and localize ``query`` in the best one.

    Ties keep the given order. When no scene has a relevant Gaussian, ``best`` is None.
    """
    if not engines:
        raise InputError("no scenes to rank", field="scenes")
    scores = [(name, scene_relevance(eng, query, stride)) for name, eng in engines.items()]
    ranking = sorted(scores, key=lambda ns: -ns[1])
    best = ranking[0][0] if ranking[0][1] > 0 else None
    loc = engines[best].localize(query, set(need)) if best is not None else None
    return SceneRanking(ranking=ranking, best=best, localization=loc)
