"""Localization within several scenes (paper §6.2).

A scene's relevance to a query is ``max_t s_t``, computed on every k-th timestep (k = 10 in the paper)
to save time; the best scene is then localized in full. Note s_t is normalized over the sampled
timesteps, so scenes of different lengths are compared as the paper does (no extra correction).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable, Mapping, Optional

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
    return rank_scenes_opening({name: (lambda e=eng: e) for name, eng in engines.items()}, query, stride=stride,
                               need=need)


def rank_scenes_opening(openers: Mapping[str, Callable[[], object]], query: str, *,
                        stride: int = DEFAULT_SCENE_STRIDE, need: Iterable[str] = ("temporal",),
                        on_scene: Optional[Callable[[str, float], None]] = None) -> SceneRanking:
    """:func:`rank_scenes` over engines opened one at a time (``openers``: {name: () -> QueryEngine}): at
    most two scenes' fields are held (the one being scored and the best so far), which then localizes.

    ``on_scene(name, relevance)`` is called after each scene is scored (progress).
    """
    if not openers:
        raise InputError("no scenes to rank", field="scenes")
    scores: list[tuple[str, float]] = []
    leader, leader_engine = None, None
    for name, open_engine in openers.items():
        engine = open_engine()
        relevance = scene_relevance(engine, query, stride)
        scores.append((name, relevance))
        if on_scene is not None:
            on_scene(name, relevance)
        if relevance > 0 and (leader is None or relevance > leader[1]):
            leader, leader_engine = (name, relevance), engine
        del engine
    ranking = sorted(scores, key=lambda ns: -ns[1])
    if leader is None:
        return SceneRanking(ranking=ranking, best=None, localization=None)
    return SceneRanking(ranking=ranking, best=leader[0], localization=leader_engine.localize(query, set(need)))
