"""``fourlegs bench query-speed --tiled-scene bench``: the codebook temporal query with exact re-scoring
timed on a real distilled field at the paper's size.

The scene's latents are tiled to N Gaussians (whole copies) x T timesteps (each timestep repeated, the
nearest source timestep), the codebook is built on the tiled field, and every query of the scene is
timed in a fresh process (so its memory is its own). The answers are checked against the exact path on
the same tiled field, computed without decoding 45M latents: copies multiply every count and repeats
weight each source timestep, so the exact per-timestep scores of the source scene determine R_avg and
every count of the tiled one.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from fourlegs_engine.errors import InputError
from .metrics import temporal_metrics
from fourlegs_engine.query.codebook import build_codebook, load_codebook
from fourlegs_engine.query.engine import QueryEngine, QueryOptions
from fourlegs_engine.query.temporal import RELEVANT, localize_counts


class TiledField:
    """The tiled latents (memmap) with the source field's decoder and canonical phrases."""

    def __init__(self, latents: np.ndarray, source: Any):
        self.latents = latents
        self.decoder = getattr(source, "decoder", None)
        self.canonical_phrases = tuple(getattr(source, "canonical_phrases", ()) or ())
        self.encoder_name = getattr(source, "encoder_name", "simulated")
        self._source = source

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return self._source.decode(z)


def source_timesteps(source_T: int, T: int) -> np.ndarray:
    """(T,) the source timestep each tiled timestep repeats (nearest, evenly spread)."""
    return np.round(np.arange(T) * (source_T - 1) / max(T - 1, 1)).astype(np.int64)


def write_tiled_latents(path: Path, source_latents: Any, T: int, N: int) -> np.ndarray:
    """Write (T,N,d) float16 latents: source timestep ``source_timesteps`` of each, Gaussians tiled."""
    T0, N0, d = (int(s) for s in source_latents.shape)
    if N % N0:
        raise InputError(f"{N} Gaussians are not whole copies of the scene's {N0}", field="--gaussians")
    out = np.lib.format.open_memmap(path, mode="w+", dtype=np.float16, shape=(T, N, d))
    for t, src in enumerate(source_timesteps(T0, T)):
        out[t] = np.tile(np.asarray(source_latents[int(src)], dtype=np.float16), (N // N0, 1))
    out.flush()
    del out
    return np.load(path, mmap_mode="r")


def exact_tiled_answers(scene: Any, field: Any, encoder: Any, queries: Sequence[str], T: int, N: int,
                        dilation: int = 1) -> dict[str, Any]:
    """The exact path's answer on the tiled field, per query, from the scene's exact scores."""
    eng = QueryEngine(scene, field, encoder, QueryOptions.exact(dilation=dilation))
    eng.temporal_many(list(queries))  # decodes each latent once and keeps every query's scores
    T0, N0 = scene.num_timesteps, scene.num_gaussians
    src = source_timesteps(T0, T)
    repeats = np.bincount(src, minlength=T0).astype(np.float64)  # tiled timesteps per source timestep
    copies = N // N0
    out = {}
    for q in queries:
        scores = np.stack([eng.gaussian_relevancy(q, t).double().numpy() for t in range(T0)])  # (T0, N0)
        rel = scores > RELEVANT
        n_rel = float(repeats @ rel.sum(axis=1))
        if n_rel == 0:
            counts = np.zeros(T, dtype=np.int64)
            r_avg = 0.0
        else:
            r_avg = float(repeats @ np.where(rel, scores, 0.0).sum(axis=1) / n_rel)
            counts = copies * (scores > r_avg).sum(axis=1).astype(np.int64)[src]
        out[q] = localize_counts(counts, np.arange(T), T, dilation=dilation, r_avg=r_avg,
                                 num_relevant=int(round(copies * n_rel)), query=q, num_gaussians=N)
    return out


def tiled_ground_truth(scene: Any, queries: Sequence[str], T: int) -> dict[str, np.ndarray]:
    """{query: (T,) bool} the scene's temporal ground truth on the tiled timesteps (each repeats its source)."""
    from .ground_truth import temporal_ground_truth

    frames = temporal_ground_truth(scene)
    src = source_timesteps(scene.num_timesteps, T)
    return {q: np.asarray(frames[q], dtype=bool)[src] for q in queries}


def tiled_query_timings(workdir: Path, size: str, k: int, margin: float, threads: int,
                        queries: Sequence[str], repeats: int = 3) -> dict:
    """Every query on the tiled field in this (fresh) process: seconds (median of ``repeats`` runs, each
    from the text embedding on; this VM's timings of one run vary by up to 2x; the first run, which also
    maps the codebook index pages its codes touch, is kept apart), answers, exact work, memory."""
    from fourlegs_engine.demo.synthetic import ensure_demo_bundle
    from fourlegs_engine.scene.bundle import load_bundle
    from .query_fixtures import scene_with_field
    from .query_fixtures import flat_scene, peak_rss_mb, resident_mb

    torch.set_num_threads(threads)
    scene, source, encoder = scene_with_field(load_bundle(ensure_demo_bundle(size)))
    lat = np.load(workdir / "tiled.npy", mmap_mode="r")
    T, N = int(lat.shape[0]), int(lat.shape[1])
    book = load_codebook(workdir / f"tiled_cb{k}", k, lat)
    if book is None:
        raise InputError(f"no codebook K={k} for the tiled latents", file=workdir)
    eng = QueryEngine(flat_scene(T, N), TiledField(lat, source), encoder, QueryOptions(path="codebook", codebook_refine=margin), codebook=book)
    eng.reference_embeddings()
    t0 = time.perf_counter()
    eng.temporal("a query that is not in the list")  # one-off: decoding the codes, opening the index,
    _ = eng.head                                      # factorizing the decoder's last layer
    first = time.perf_counter() - t0
    rows = []
    for q in queries:
        eng.embed_query(q)  # text encoding is the encoder's cost, timed apart
        before = dict(eng.stats)
        times = []
        for _ in range(repeats):  # the same work each time (the query seeds its own samples)
            eng.forget_query(q)   # its code relevancies too: every run scores the codes again
            t0 = time.perf_counter()
            res = eng.temporal(q)
            times.append(time.perf_counter() - t0)
        done = {key: int(eng.stats[key] - before.get(key, 0)) // repeats
                for key in ("rescored_latents", "sampled_latents", "bounded_latents")}
        rows.append({"query": q, "seconds": float(np.median(times)), "times_s": times, "first_run_s": times[0],
                     "segment": list(res.segment) if res.segment else None, "positive": res.positive.tolist(),
                     "rescored": done["rescored_latents"], "sampled": done["sampled_latents"],
                     "bounded": done["bounded_latents"]})
    return {"first_query_s": first, "queries": rows, "peak_rss_mb": peak_rss_mb(),
            "anon_rss_mb": resident_mb("RssAnon"), "file_rss_mb": resident_mb("RssFile")}


def run_tiled_query_speed(size: str, *, gaussians: int, timesteps: int, codebook_sizes: Sequence[int],
                          margins: Sequence[float], workdir: Path, progress: bool = True) -> list[dict]:
    """Rows of the tiled benchmark: one per (K, margin), each with its per-query times and answers."""
    import multiprocessing

    from .ground_truth import scene_queries
    from fourlegs_engine.demo.synthetic import ensure_demo_bundle
    from fourlegs_engine.scene.bundle import load_bundle
    from .query_fixtures import scene_with_field
    from .query_fixtures import warm_page_cache

    scene, field, encoder = scene_with_field(load_bundle(ensure_demo_bundle(size)), progress=progress)
    queries = list(scene_queries(scene))
    T, N = int(timesteps), int(gaussians)
    t0 = time.perf_counter()
    lat = write_tiled_latents(workdir / "tiled.npy", field.latents, T, N)
    write_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    exact = exact_tiled_answers(scene, field, encoder, queries, T, N)
    exact_s = time.perf_counter() - t0
    truth = tiled_ground_truth(scene, queries, T)
    spawn = multiprocessing.get_context("spawn")
    rows = []
    for K in codebook_sizes:
        t0 = time.perf_counter()
        build_codebook(lat, K, out_dir=workdir / f"tiled_cb{K}", progress=progress)
        build = time.perf_counter() - t0
        for margin in [m for m in margins if m > 0]:
            cache_s = warm_page_cache(workdir / "tiled.npy")  # as the random-latent rows: reads are from memory
            with spawn.Pool(1) as pool:
                got = pool.apply(tiled_query_timings, (workdir, size, K, margin, torch.get_num_threads(), queries))
            got["page_cache_warm_s"] = cache_s
            per_query = got.pop("queries")
            for r in per_query:
                want = exact[r["query"]]
                r["exact_segment"] = list(want.segment) if want.segment else None
                r["equal_to_exact"] = r["segment"] == r["exact_segment"] and r["positive"] == want.positive.tolist()
                # the benchmark's tIoU (positive timesteps against the ground truth) of both answers
                r["tIoU"] = temporal_metrics(np.asarray(r.pop("positive"), dtype=bool), truth[r["query"]])["tIoU"]
                r["exact_tIoU"] = temporal_metrics(want.positive, truth[r["query"]])["tIoU"]
            found = [r for r in per_query if r["exact_segment"] is not None]
            seconds = [r["seconds"] for r in per_query]
            row = {"path": f"codebook K={K} + exact re-scoring ±{margin:g} on the {size} field tiled to "
                           f"{N:,} x {T}", "scene": size, "num_gaussians": N, "num_timesteps": T,
                   "codebook_size": K, "refine_margin": margin, "build_s": build, "write_latents_s": write_s,
                   "exact_reference_s": exact_s, "mean_query_s": float(np.mean(seconds)),
                   "max_query_s": float(np.max(seconds)),
                   "mean_found_query_s": float(np.mean([r["seconds"] for r in found])) if found else float("nan"),
                   "equal_to_exact": sum(r["equal_to_exact"] for r in per_query), "num_queries": len(per_query),
                   "tIoU": float(np.mean([r["tIoU"] for r in per_query])),
                   "exact_tIoU": float(np.mean([r["exact_tIoU"] for r in per_query])),
                   "queries": per_query, **got, "rss_scope": "query process"}
            rows.append(row)
            print(f"  {row['path']}: mean {row['mean_query_s']:.3f} s per query (max {row['max_query_s']:.3f}, "
                  f"found {row['mean_found_query_s']:.3f}); {row['equal_to_exact']}/{row['num_queries']} equal "
                  f"to exact; tIoU {100 * row['tIoU']:.1f} (exact {100 * row['exact_tIoU']:.1f})", file=sys.stderr)
    return rows


def markdown_rows(rows: Sequence[dict]) -> list[str]:
    if not rows:
        return []
    lines = ["", "Real field at that size: the scene's distilled latents tiled (copies x repeated timesteps), "
             "every row in a fresh process, each query's time the median of 3 runs, answers checked against the "
             "exact path on the same tiled field:", "",
             "| path | mean s per query | queries that find something (s) | slowest (s) | answers equal to exact | "
             "tIoU (exact path's) | exact latents per query (sampled + re-scored; decided by norm bounds) | "
             "own memory (MB) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        q = r["queries"]
        sampled = int(np.mean([x["sampled"] for x in q]))
        rescored = int(np.mean([x["rescored"] for x in q]))
        bounded = int(np.mean([x.get("bounded", 0) for x in q]))
        lines.append(f"| {r['path']} | {r['mean_query_s']:.3f} | {r['mean_found_query_s']:.3f} | "
                     f"{r['max_query_s']:.3f} | {r['equal_to_exact']}/{r['num_queries']} | "
                     f"{100 * r['tIoU']:.1f} ({100 * r['exact_tIoU']:.1f}) | {sampled} + {rescored}; {bounded} | "
                     f"{r['anon_rss_mb']:.0f} |")
    return lines
