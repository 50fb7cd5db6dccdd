"""The field's in-between timesteps of a ``fill="latents"`` extraction: lifted from no features, filled from
the lifted timesteps around them.

Only the timesteps on the stride's grid have teacher features and are lifted. Every other timestep t
between grid timesteps a < t < b gives each Gaussian i the normalized linear interpolation of its own
latents, L_i(t) ∝ (1 - w) L_i(a) + w L_i(b) with w = (t - a) / (b - a). A Gaussian that moves with its
object carries its latent along, so the fill follows the motion (the crop-feature fills interpolate at
fixed pixel positions and smear a moving object between its two encoded places). A Gaussian no view of
either neighbour saw keeps a zero latent; one seen at a single neighbour takes that neighbour's latent.
"""
from __future__ import annotations

from typing import Any, Sequence

from .plans import LATENT_FILLS
from .skipping import encoded_timesteps, fill_features, fill_sources, timestep_work
from .store import StepStore, parse_shard, select_timesteps


def latent_fill_of(features_config: dict[str, Any]) -> int | None:
    """The timestep stride whose in-between timesteps the lift fills (None: the features cover every timestep)."""
    if str(features_config.get("fill", "interpolate")) not in LATENT_FILLS:
        return None
    return int(features_config.get("timestep_stride", 1))


def lift_and_fill_work(num_timesteps: int, stride: int | None, timesteps: Any = None,
                       shard: Any = None) -> tuple[list[int], list[int]]:
    """(timesteps to lift, timesteps to fill) of one worker: without a latent fill the selection itself
    and nothing; with one, the selection's grid timesteps and the grid neighbours its in-between timesteps
    need, and those in-between timesteps (each list sharded like the extraction's)."""
    if stride is None:
        return select_timesteps(num_timesteps, timesteps, shard), []
    parts = parse_shard(shard) if shard is None or isinstance(shard, str) else tuple(shard)
    return timestep_work(num_timesteps, select_timesteps(num_timesteps, timesteps), stride, LATENT_FILLS[0], parts)


def fill_latent_steps(store: StepStore, to_fill: Sequence[int], stride: int) -> list[int]:
    """Write the latents (N, d) float16 of the in-between timesteps whose lifted neighbours are finished;
    returns the timesteps written (the others wait for a run that finishes their neighbours)."""
    grid = encoded_timesteps(store.num_timesteps, stride)
    filled = []
    for t in to_fill:
        if store.is_done(t):
            continue
        sources = fill_sources(t, grid, LATENT_FILLS[0])
        if all(store.is_done(k) for k, _ in sources):
            store.save(t, fill_features([(store.load_verified(k), w) for k, w in sources]))
            filled.append(int(t))
    return filled
