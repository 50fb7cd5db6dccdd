"""Tile rasterizer in pure torch with a hand-written backward.

Each tile owns a depth-sorted list of Gaussians (:mod:`.binning`). Tiles are processed in batches,
and every batch walks its lists front to back ``chunk`` entries at a time: a chunk is a dense
(b, P, K) problem (b tiles still running, P = tile_size² pixels, K list entries) whose exponents are one
(P,6) @ (b,6,K) matmul (see :class:`TileGeometry`), whose transmittance is a cumulative product
continued from the previous chunk, and whose channels are blended by one batched matmul
((b,P,K) weights @ (b,K,C)) for any C. Tiles whose pixels have all stopped (T would fall below
``transmittance_min``) leave the loop, so deeply stacked tiles cost only their visible front.

The backward replays the chunk loop to recover each chunk's starting transmittance (nothing of size
P·K is kept between passes), then visits the chunks back to front, carrying the reverse cumulative
sum that the transmittance gradient needs:

    out_p   = Σ_i w_i v_i + T_final·bg,     w_i = α_i T_i,     T_i = Π_{j<i} (1 − α_j)
    ∂L/∂α_i = T_i s_i − (Σ_{k>i} w_k s_k + T_final ∂L/∂T_final) / (1 − α_i),   s_i = ∂L/∂w_i = g_p·v_i

The background term is applied outside (plain autograd), so the kernel returns Σ w v and T_final.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import torch

from .binning import Binning
from .options import RasterOptions

GEOM_CHANNELS = 6  # mx, my, conic a, b, c, opacity


@dataclass
class RasterResult:
    """Raw results on the tile-padded pixel grid (Hp·Wp rows, row-major; see :func:`tiles_to_image`).

    Attributes:
        accum: (Hp·Wp, C) Σ w·values.
        transmittance: (Hp·Wp,) final transmittance (1 − alpha).
        median_ids: (Hp·Wp,) int64 Gaussian at the median of the weight distribution, −1 if none;
            None unless requested.
        weights: (pixel, gaussian, weight) rows or None unless requested.
        splatted: (N, S) Σ_p w_i(p)·splat(p) per Gaussian (the adjoint of blending) or None unless
            ``splat`` values were given.
    """

    accum: torch.Tensor
    transmittance: torch.Tensor
    median_ids: torch.Tensor | None
    weights: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None
    splatted: torch.Tensor | None = None


def tile_batches(binning: Binning, budget: int, chunk: int) -> Iterator[tuple[torch.Tensor, int]]:
    """Yield (tile indices (B,), longest list length K) covering every non-empty tile once.

    Tiles are taken in decreasing list length, B = budget // (P·chunk) at a time (a batch is processed
    ``chunk`` list entries at a time, so its working set is at most ``budget`` pixel×Gaussian pairs).
    """
    counts = binning.tile_counts
    P = binning.tile_size ** 2
    nonempty = torch.nonzero(counts > 0).squeeze(1)
    if nonempty.numel() == 0:
        return
    c_sorted, idx = torch.sort(counts[nonempty], descending=True)
    tiles = nonempty[idx]
    step = max(1, budget // (P * chunk))
    c_list = c_sorted.tolist()
    for i in range(0, len(c_list), step):
        yield tiles[i:i + step], c_list[i]


def _below(x: float, dtype: torch.dtype) -> float:
    """The largest ``dtype`` number smaller than ``x``."""
    t = torch.tensor(x, dtype=dtype)
    return float(torch.nextafter(t, torch.zeros_like(t)))


class TileGeometry:
    """Per-batch constants: tile origins, list starts/lengths, and the pixel basis Φ.

    The exponent of every (pixel, Gaussian) pair is a quadratic in the tile-local pixel centre
    (lx, ly): power = Φ(lx, ly) · coef, Φ = [lx², lx·ly, ly², lx, ly, 1], so a whole chunk of exponents
    is one (P,6) @ (B,6,K) matmul. Coordinates are tile-local, so the expansion loses no precision.
    """

    def __init__(self, binning: Binning, tiles: torch.Tensor, dtype: torch.dtype):
        ts = binning.tile_size
        device = tiles.device
        self.tiles = tiles
        self.start = binning.tile_offsets[tiles]
        self.count = binning.tile_offsets[tiles + 1] - self.start
        self.x0 = ((tiles % binning.tiles_x) * ts).to(dtype)
        self.y0 = ((tiles // binning.tiles_x) * ts).to(dtype)
        p = torch.arange(ts * ts, device=device)
        lx = (p % ts).to(dtype) + 0.5
        ly = (p // ts).to(dtype) + 0.5
        self.phi = torch.stack([lx * lx, lx * ly, ly * ly, lx, ly, torch.ones_like(lx)], dim=-1)  # (P,6)
        self.px_int = (tiles % binning.tiles_x)[:, None] * ts + p % ts  # (B,P) int64
        self.py_int = (tiles // binning.tiles_x)[:, None] * ts + p // ts
        self.pix = (self.py_int * (binning.tiles_x * ts) + self.px_int).reshape(-1)  # (B·P,) padded-grid rows


def pair_coefficients(geom: torch.Tensor, binning: Binning) -> tuple[torch.Tensor, torch.Tensor]:
    """Exponent coefficients of every (tile, Gaussian) pair, plus a sentinel row.

    Returns:
        coef: (M+1, 6) [−a/2, −b, −c/2, a·ux + b·uy, b·ux + c·uy, −½(a ux² + 2b ux uy + c uy²) + ln o] with
            (ux, uy) the mean relative to the pair's tile origin; row M is the sentinel (exponent −inf,
            i.e. α = 0) used to pad lists.
        gids: (M+1,) Gaussian ids with the sentinel mapped to 0.
    """
    ts = binning.tile_size
    gids = binning.gaussian_ids
    tile = binning.pair_tiles.to(torch.int64)
    mx, my, ca, cb, cc, o = geom.index_select(0, gids).unbind(-1)
    ux = mx - ((tile % binning.tiles_x) * ts).to(geom.dtype)
    uy = my - ((tile // binning.tiles_x) * ts).to(geom.dtype)
    M = gids.shape[0]
    coef = torch.empty(M + 1, 6, dtype=geom.dtype, device=geom.device)
    torch.mul(ca, -0.5, out=coef[:M, 0])
    torch.neg(cb, out=coef[:M, 1])
    torch.mul(cc, -0.5, out=coef[:M, 2])
    torch.addcmul(ca * ux, cb, uy, out=coef[:M, 3])
    torch.addcmul(cb * ux, cc, uy, out=coef[:M, 4])
    # −½(a ux² + c uy²) − b ux uy + ln o  =  −½ ux·coef3 − ½ uy·coef4 + ln o
    coef[:M, 5] = torch.log(o) - 0.5 * (ux * coef[:M, 3] + uy * coef[:M, 4])
    coef[M] = torch.tensor([0, 0, 0, 0, 0, -torch.inf], dtype=geom.dtype, device=geom.device)
    gid_table = torch.zeros(M + 1, dtype=gids.dtype, device=gids.device)
    gid_table[:M] = gids
    return coef, gid_table


class Chunk:
    """List entries [j0, j0+K) of the tiles ``rows`` (indices into the batch) and their α."""

    def __init__(self, tables: tuple[torch.Tensor, torch.Tensor], tg: TileGeometry, rows: torch.Tensor,
                 j0: int, k: int, opts: RasterOptions, for_backward: bool = False):
        coef_table, gid_table = tables
        sentinel = coef_table.shape[0] - 1
        ar = torch.arange(j0, j0 + k, device=coef_table.device)
        self.rows = rows
        self.valid = ar[None, :] < tg.count[rows, None]  # (b,K)
        pos = torch.where(self.valid, tg.start[rows, None] + ar[None, :], torch.full_like(ar, sentinel)[None, :])
        self.pos = pos.reshape(-1)
        self.gid = gid_table.index_select(0, self.pos).view(pos.shape)  # (b,K)
        coef = coef_table.index_select(0, self.pos).view(pos.shape + (6,))
        alpha = torch.matmul(tg.phi, coef.transpose(1, 2)).exp_()  # (b,P,K) = o·G
        if for_backward:
            self.unclamped = alpha < opts.alpha_max
        alpha.clamp_(max=opts.alpha_max)
        # α < alpha_min → 0 in one fused pass (threshold keeps x > t; t = the float just below alpha_min)
        torch.nn.functional.threshold_(alpha, _below(opts.alpha_min, alpha.dtype), 0.0)
        self.alpha = alpha

    def blend(self, t_start: torch.Tensor, done: torch.Tensor, opts: RasterOptions
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """Front-to-back blending from transmittance ``t_start`` (b,P) for pixels not ``done`` (b,P).

        Zeroes α where not blended. Returns T before each entry (b,P,K), the transmittance after the
        chunk (b,P), the updated done flags (b,P) and the inclusive transmittance (b,P,K).
        """
        alpha = self.alpha
        t_incl = torch.cumprod(1.0 - alpha, dim=-1).mul_(t_start[..., None])
        blend = (t_incl >= opts.transmittance_min) & ~done[..., None]
        alpha.mul_(blend)
        t_excl = torch.empty_like(t_incl)
        t_excl[..., 0] = t_start
        t_excl[..., 1:] = t_incl[..., :-1]
        t_end = torch.where(blend, t_incl, t_start[..., None]).amin(dim=-1)
        done = done | (t_incl[..., -1] < opts.transmittance_min)
        return t_excl, t_end, done, t_incl


def _chunks(tables, tg: TileGeometry, k_max: int, opts: RasterOptions, chunk: int, t_state: torch.Tensor,
            done: torch.Tensor):
    """Run the batch front to back, yielding (Chunk, t_start, done_start, t_excl, t_end, t_incl)
    per chunk; ``t_state``/``done`` (B,P) are updated in place. Tiles whose pixels are all done, or
    whose lists are exhausted, leave the loop early."""
    rows = torch.arange(tg.tiles.shape[0], device=t_state.device)
    for j0 in range(0, k_max, chunk):
        alive = (tg.count[rows] > j0) & ~done[rows].all(dim=-1)
        rows = rows[alive]
        if rows.numel() == 0:
            return
        ch = Chunk(tables, tg, rows, j0, min(chunk, k_max - j0), opts)
        t_start, d_start = t_state[rows], done[rows]
        t_excl, t_end, d_end, t_incl = ch.blend(t_start, d_start, opts)
        t_state[rows] = t_end
        done[rows] = d_end
        yield ch, t_start, d_start, t_excl, t_end, t_incl


def rasterize_forward(geom: torch.Tensor, values: torch.Tensor, binning: Binning, opts: RasterOptions,
                      want_median: bool = False, want_weights: bool = False,
                      splat: torch.Tensor | None = None, splat_out: torch.Tensor | None = None) -> RasterResult:
    """Blend every tile front to back (no autograd).

    Args:
        geom: (N,6) mx, my, conic a, b, c, opacity. values: (N,C) channels to blend (C may be 0).
        splat: (Hp·Wp, S) per-pixel values on the tile-padded grid (zero outside the image), or None.
            When given, ``splatted`` (N,S) = Σ_p w_i(p)·splat(p) is accumulated in the same pass — the
            transpose of blending, without materializing the weights.
        splat_out: (N, S) working-dtype tensor the splatted sums are added to (and returned as
            ``splatted``) instead of a new zero tensor.
    """
    P = binning.tile_size ** 2
    n_tiles = binning.num_tiles
    device, dtype = geom.device, geom.dtype
    C = values.shape[1]
    chunk = opts.chunk
    n_pix = n_tiles * P
    accum = torch.zeros(n_pix, C, device=device, dtype=dtype)
    t_final_all = torch.ones(n_pix, device=device, dtype=dtype)
    median = torch.full((n_pix,), -1, device=device, dtype=torch.int64) if want_median else None
    rows_out: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []
    splatted = None
    if splat is not None:
        S = splat.shape[1]
        splatted = torch.zeros(geom.shape[0], S, device=device, dtype=dtype) if splat_out is None else splat_out
    with torch.no_grad():
        tables = pair_coefficients(geom, binning)
        for tiles, k_max in tile_batches(binning, opts.batch_elements, chunk):
            tg = TileGeometry(binning, tiles, dtype)
            B = tiles.shape[0]
            t_state = torch.ones(B, P, device=device, dtype=dtype)
            done = torch.zeros(B, P, device=device, dtype=torch.bool)
            acc = torch.zeros(B, P, C, device=device, dtype=dtype)
            g_all = splat.index_select(0, tg.pix).view(B, P, S).to(dtype) if splat is not None else None
            for ch, _, _, t_excl, _, _ in _chunks(tables, tg, k_max, opts, chunk, t_state, done):
                w = ch.alpha.mul_(t_excl)
                if splat is not None:
                    # padded list entries have w = 0 (sentinel α = 0), so they add nothing to Gaussian 0
                    splatted.index_add_(0, ch.gid.reshape(-1),
                                        torch.bmm(w.transpose(1, 2), g_all[ch.rows]).reshape(-1, S))
                if C:
                    vals = values.index_select(0, ch.gid.reshape(-1)).view(ch.gid.shape + (C,))
                    acc[ch.rows] += torch.bmm(w, vals.to(dtype))
                if want_weights:
                    inside = (tg.px_int[ch.rows] < binning.width) & (tg.py_int[ch.rows] < binning.height)
                    b, p, kk = torch.nonzero((w > 0) & inside[..., None], as_tuple=True)
                    r = ch.rows[b]
                    rows_out.append((tg.py_int[r, p] * binning.width + tg.px_int[r, p], ch.gid[b, kk], w[b, p, kk]))
            if C:
                accum.index_copy_(0, tg.pix, acc.reshape(-1, C))
            t_final_all.index_copy_(0, tg.pix, t_state.reshape(-1))
            if want_median:
                median.index_copy_(0, tg.pix, _median_ids(tables, tg, k_max, opts, chunk, t_state).reshape(-1))
    weights = None
    if want_weights:
        if rows_out:
            pix = torch.cat([r[0] for r in rows_out])
            gid = torch.cat([r[1] for r in rows_out])
            wt = torch.cat([r[2] for r in rows_out])
            order = torch.sort(pix, stable=True).indices
            weights = (pix[order], gid[order], wt[order])
        else:
            empty = torch.zeros(0, dtype=torch.int64, device=device)
            weights = (empty, empty.clone(), torch.zeros(0, dtype=dtype, device=device))
    return RasterResult(accum=accum, transmittance=t_final_all, median_ids=median, weights=weights,
                        splatted=splatted)


def _median_ids(tables, tg, k_max, opts, chunk, t_final) -> torch.Tensor:
    """(B,P) id of the first Gaussian where the accumulated weight 1 − T reaches half of the pixel's
    alpha, i.e. T_incl ≤ (1 + T_final)/2; −1 where nothing is drawn (a second pass over the batch)."""
    B, P = t_final.shape
    device = t_final.device
    thresh = 0.5 * (1.0 + t_final)
    ids = torch.full((B, P), -1, dtype=torch.int64, device=device)
    found = t_final >= 1.0  # nothing drawn: never search
    t_state = torch.ones_like(t_final)
    done = torch.zeros_like(found)
    for ch, _, _, _, _, t_incl in _chunks(tables, tg, k_max, opts, chunk, t_state, done):
        hit = (t_incl <= thresh[ch.rows, :, None]) & (ch.alpha > 0) & ~found[ch.rows, :, None]
        any_hit = hit.any(-1)
        first = hit.to(torch.int8).argmax(dim=-1)
        picked = torch.gather(ch.gid, 1, first)
        r = ch.rows
        ids[r] = torch.where(any_hit, picked, ids[r])
        found[r] |= any_hit
    return ids


def rasterize_backward(geom: torch.Tensor, values: torch.Tensor, binning: Binning, opts: RasterOptions,
                       grad_accum: torch.Tensor, grad_t: torch.Tensor, t_final_all: torch.Tensor,
                       need_values_grad: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Gradients of Σ w·v and T_final w.r.t. geom (N,6) and values (N,C).

    Per batch, the forward chunk loop is replayed to recover each chunk's starting transmittance,
    then the chunks are visited back to front carrying Σ_{later} w·s (the reverse cumulative sum).
    """
    N, C = values.shape
    P = binning.tile_size ** 2
    device, dtype = geom.device, geom.dtype
    chunk = opts.chunk
    grad_geom = torch.zeros(N, GEOM_CHANNELS, device=device, dtype=dtype)
    grad_values = torch.zeros(N, C, device=device, dtype=dtype) if need_values_grad else None
    with torch.no_grad():
        tables = pair_coefficients(geom, binning)
        for tiles, k_max in tile_batches(binning, opts.batch_elements, chunk):
            tg = TileGeometry(binning, tiles, dtype)
            B = tiles.shape[0]
            t_state = torch.ones(B, P, device=device, dtype=dtype)
            done = torch.zeros(B, P, device=device, dtype=torch.bool)
            starts = [(ch.rows, j0, t_start, d_start) for j0, (ch, t_start, d_start, *_) in
                      zip(range(0, k_max, chunk), _chunks(tables, tg, k_max, opts, chunk, t_state, done))]
            g_all = grad_accum.index_select(0, tg.pix).view(B, P, C) if C else None
            # the T_final term of ∂L/∂α: every blended entry is followed by T_final·∂L/∂T_final
            carry = t_state * grad_t.index_select(0, tg.pix).view(B, P)
            for rows, j0, t_start, d_start in reversed(starts):
                ch = Chunk(tables, tg, rows, j0, min(chunk, k_max - j0), opts, for_backward=True)
                t_excl, _, _, _ = ch.blend(t_start, d_start, opts)
                alpha = ch.alpha
                w = alpha * t_excl
                if C:
                    g = g_all[rows]
                    vals = values.index_select(0, ch.gid.reshape(-1)).view(ch.gid.shape + (C,)).to(dtype)
                    s = torch.bmm(g, vals.transpose(1, 2))  # (b,P,K) ∂L/∂w
                    if need_values_grad:
                        grad_values.index_add_(0, ch.gid.reshape(-1), torch.bmm(w.transpose(1, 2), g).reshape(-1, C))
                    ws = s * w
                    cs = torch.cumsum(ws, dim=-1)
                    total = cs[..., -1].clone()
                    suffix = cs.neg_().add_((total + carry[rows])[..., None])  # Σ_{k>i} w_k s_k (+ T_final term)
                    carry[rows] += total
                    d_alpha = s.mul_(t_excl)
                else:
                    suffix = carry[rows][..., None].expand_as(alpha)
                    d_alpha = torch.zeros_like(alpha)
                d_alpha.sub_(suffix / (1.0 - alpha))
                d_power = d_alpha.mul_(alpha).mul_((alpha > 0) & ch.unclamped)  # ∂L/∂power, α = exp(power)
                d_coef = torch.matmul(tg.phi.T, d_power)  # (b,6,K)
                grads = _coef_to_geom_grads(ch, d_coef, geom, tg)
                grads = torch.where(ch.valid[..., None], grads, torch.zeros_like(grads))
                grad_geom.index_add_(0, ch.gid.reshape(-1), grads.reshape(-1, GEOM_CHANNELS))
    return grad_geom, grad_values


def _coef_to_geom_grads(ch: Chunk, d_coef: torch.Tensor, geom: torch.Tensor, tg: TileGeometry) -> torch.Tensor:
    """Chain ∂L/∂coef (b,6,K) to ∂L/∂(mx, my, a, b, c, o) (b,K,6); see :func:`pair_coefficients`."""
    d0, d1, d2, d3, d4, d5 = d_coef.unbind(1)
    mx, my, ca, cb, cc, o = geom.index_select(0, ch.gid.reshape(-1)).view(ch.gid.shape + (6,)).unbind(-1)
    ux = mx - tg.x0[ch.rows, None]
    uy = my - tg.y0[ch.rows, None]
    d_ca = -0.5 * d0 + ux * d3 - 0.5 * ux * ux * d5
    d_cb = -d1 + uy * d3 + ux * d4 - ux * uy * d5
    d_cc = -0.5 * d2 + uy * d4 - 0.5 * uy * uy * d5
    d_ux = ca * d3 + cb * d4 - (ca * ux + cb * uy) * d5
    d_uy = cb * d3 + cc * d4 - (cb * ux + cc * uy) * d5
    d_o = d5 / o
    return torch.stack([d_ux, d_uy, d_ca, d_cb, d_cc, d_o], dim=-1)


class RasterizeTiles(torch.autograd.Function):
    """(geom (N,6), values (N,C)) -> (accum (Hp·Wp,C), T_final (Hp·Wp,), median ids, weights)."""

    @staticmethod
    def forward(ctx, geom, values, binning, opts, want_median, want_weights):  # noqa: D401
        res = rasterize_forward(geom, values, binning, opts, want_median, want_weights)
        ctx.binning, ctx.opts = binning, opts
        ctx.save_for_backward(geom, values, res.transmittance)
        median = res.median_ids if res.median_ids is not None else torch.zeros(0, dtype=torch.int64)
        if res.weights is not None:
            pix, gid, wt = res.weights
        else:
            pix = gid = torch.zeros(0, dtype=torch.int64)
            wt = torch.zeros(0, dtype=geom.dtype)
        ctx.mark_non_differentiable(median, pix, gid, wt)
        return res.accum, res.transmittance, median, pix, gid, wt

    @staticmethod
    def backward(ctx, grad_accum, grad_t, *_):
        geom, values, t_final = ctx.saved_tensors
        if grad_accum is None:
            grad_accum = torch.zeros(ctx.binning.num_tiles * ctx.binning.tile_size ** 2, values.shape[1],
                                     dtype=geom.dtype, device=geom.device)
        if grad_t is None:
            grad_t = torch.zeros_like(t_final)
        grad_geom, grad_values = rasterize_backward(
            geom, values, ctx.binning, ctx.opts, grad_accum.contiguous(), grad_t.contiguous(), t_final,
            ctx.needs_input_grad[1])
        if grad_values is not None:
            grad_values = grad_values.to(values.dtype)
        return grad_geom, grad_values, None, None, None, None


def tiles_to_image(buffer: torch.Tensor, binning: Binning) -> torch.Tensor:
    """(Hp·Wp, C) rows of the tile-padded grid -> (H, W, C) image view (differentiable, no copy)."""
    ts = binning.tile_size
    img = buffer.reshape(binning.tiles_y * ts, binning.tiles_x * ts, -1)
    return img[:binning.height, :binning.width]
