"""Tile binning: which Gaussians touch which square pixel tile, front to back.

Each visible Gaussian is paired with every tile its pixel bounds overlap; the pairs are sorted by
(tile, depth) so every tile owns a contiguous, depth-ordered run of Gaussian ids.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from .projection import Projected


@dataclass
class Binning:
    """Depth-sorted Gaussian lists per tile.

    Attributes:
        gaussian_ids: (M,) int64 Gaussian index of each (tile, Gaussian) pair, grouped by tile and
            front to back inside a tile (ties in depth broken by index).
        pair_tiles: (M,) int32 tile of each pair (non-decreasing).
        tile_offsets: (n_tiles + 1,) int64: tile t owns ``gaussian_ids[tile_offsets[t]:tile_offsets[t+1]]``.
        tiles_x, tiles_y: tile grid size; tile t covers pixels x in [tx·s, tx·s + s), y likewise,
            with t = ty·tiles_x + tx.
        tile_size: s.
        width, height: image size.
    """

    gaussian_ids: torch.Tensor
    pair_tiles: torch.Tensor
    tile_offsets: torch.Tensor
    tiles_x: int
    tiles_y: int
    tile_size: int
    width: int
    height: int

    @property
    def num_tiles(self) -> int:
        return self.tiles_x * self.tiles_y

    @property
    def tile_counts(self) -> torch.Tensor:
        return self.tile_offsets[1:] - self.tile_offsets[:-1]

    @property
    def num_pairs(self) -> int:
        return int(self.gaussian_ids.shape[0])


#: tile sides "auto" chooses from
AUTO_TILE_SIZES = (4, 8, 16)
#: cost of one tile–Gaussian pair (sorting, gathering, per-pair coefficients) in units of one
#: pixel evaluation of a 3-channel blend
PAIR_COST = 64.0
#: every this many blended channels add one more pixel-evaluation unit
CHANNELS_PER_UNIT = 16.0


def estimated_pairs(proj: Projected, tile_size: int) -> float:
    """Expected number of tile–Gaussian pairs at ``tile_size`` for the visible Gaussians: a box of
    w×h pixels at a random offset overlaps ((w−1)/s + 1)·((h−1)/s + 1) tiles of side s on average."""
    with torch.no_grad():
        b = proj.bounds[proj.visible].to(torch.float64)
        if b.shape[0] == 0:
            return 0.0
        w = b[:, 1] - b[:, 0]
        h = b[:, 3] - b[:, 2]
        return float(((w / tile_size + 1) * (h / tile_size + 1)).sum())


def choose_tile_size(proj: Projected, channels: int = 3, candidates: tuple[int, ...] = AUTO_TILE_SIZES) -> int:
    """The tile side minimizing pairs·(PAIR_COST + s²·(1 + channels/CHANNELS_PER_UNIT)): the work of
    binning/sorting the pairs plus the s² pixel evaluations each pair costs, each blending ``channels``
    values. Many channels (latent features) favour small tiles; large overlapping splats large ones."""
    per_pixel = 1.0 + channels / CHANNELS_PER_UNIT
    costs = [estimated_pairs(proj, s) * (PAIR_COST + s * s * per_pixel) for s in candidates]
    return candidates[min(range(len(candidates)), key=lambda i: (costs[i], candidates[i]))]


def resolve_tile_size(proj: Projected, tile_size: int | str, channels: int = 3) -> int:
    """``tile_size`` itself, or :func:`choose_tile_size` for ``"auto"``."""
    return choose_tile_size(proj, channels) if tile_size == "auto" else int(tile_size)


def bin_gaussians(proj: Projected, width: int, height: int, tile_size: int | str, channels: int = 3) -> Binning:
    """Pair visible Gaussians with the tiles their pixel bounds overlap, sorted by (tile, depth).
    ``tile_size`` may be ``"auto"`` (:func:`choose_tile_size` for ``channels`` blended values)."""
    tile_size = resolve_tile_size(proj, tile_size, channels)
    device = proj.depths.device
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    n_tiles = tiles_x * tiles_y
    with torch.no_grad():
        vis = torch.nonzero(proj.visible).squeeze(1)
        order = vis.index_select(0, torch.sort(proj.depths.detach().index_select(0, vis), stable=True).indices)  # front to back
        b = proj.bounds.index_select(0, order)
        tx0, tx1 = b[:, 0] // tile_size, b[:, 1] // tile_size
        ty0, ty1 = b[:, 2] // tile_size, b[:, 3] // tile_size
        span_x = tx1 - tx0 + 1
        counts = span_x * (ty1 - ty0 + 1)
        n_vis = int(order.shape[0])
        rank = torch.repeat_interleave(torch.arange(n_vis, device=device), counts)
        starts = torch.cumsum(counts, 0) - counts
        local = torch.arange(rank.shape[0], device=device) - starts.index_select(0, rank)
        sx = span_x.index_select(0, rank)
        # local // sx in float64 (exact for these small integers; int64 division is slow)
        row = torch.floor(local.to(torch.float64) / sx.to(torch.float64)).to(torch.int64)
        col = local - row * sx
        tile = ((ty0.index_select(0, rank) + row) * tiles_x + (tx0.index_select(0, rank) + col)).to(torch.int32)
        # pairs are generated front to back, so a stable sort by tile keeps the depth order inside tiles
        pair_tiles, perm = torch.sort(tile, stable=True)
        gaussian_ids = order.index_select(0, rank.index_select(0, perm))
        per_tile = torch.bincount(pair_tiles, minlength=n_tiles)
        offsets = torch.zeros(n_tiles + 1, dtype=torch.int64, device=device)
        offsets[1:] = torch.cumsum(per_tile, 0)
    return Binning(gaussian_ids=gaussian_ids, pair_tiles=pair_tiles, tile_offsets=offsets, tiles_x=tiles_x, tiles_y=tiles_y,
                   tile_size=tile_size, width=width, height=height)
