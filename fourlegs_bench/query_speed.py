"""``fourlegs bench query-speed``: query timings at the paper's scale without distilling a scene.

Random unit latents (T,N,128) float16 — the dtype the language stage stores — are written as a memmap in
a temporary directory, decoded by a randomly initialized decoder of the real architecture
(128→256→512→768, L2-normalized). Timed: the codebook build (once per scene), the temporal query on the
codebook path (cold: includes decoding the K codes once; warm: a further query), optionally with
exact re-scoring near the thresholds (``--refine``), the exact path
(``--exact-timesteps`` timesteps timed and extrapolated to all T, stated as such), and relevancy maps at
640×360 on the geometry of a synthetic scene (fast 1-channel and exact 128-channel paths).

Each codebook query row runs in a fresh process (multiprocessing "spawn") that opens the stored codebook
and the latents memmap the way ``fourlegs query`` does, so its peak RSS (``resource.getrusage``) is the
query's own footprint, not the parent's, which wrote the 11.5 GB memmap and built the codebooks.
"""
from __future__ import annotations

import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from fourlegs_engine.errors import InputError, OutputExistsError
from fourlegs_engine.fileio import write_json_atomic
from fourlegs_engine.query.codebook import build_codebook
from fourlegs_engine.query.engine import QueryEngine, QueryOptions

from .query_fixtures import flat_scene, peak_rss_mb, resident_mb, warm_page_cache

QUERY = "a ball flying in the air"


class RandomField:
    """A language field with random latents (memmap) and a random decoder of the real architecture."""

    encoder_name = "simulated"
    canonical_phrases = ("object", "things", "stuff", "texture")

    def __init__(self, latents: np.ndarray, seed: int = 0):
        from fourlegs_engine.language.autoencoder import FeatureDecoder

        torch.manual_seed(seed)
        self.latents = latents
        self.decoder = FeatureDecoder((latents.shape[-1], 256, 512, 768)).eval()

    @torch.no_grad()
    def decode(self, z: torch.Tensor) -> torch.Tensor:
        return self.decoder(torch.as_tensor(z, dtype=torch.float32))


def random_latents(path: Path, T: int, N: int, d: int = 128, seed: int = 0) -> np.ndarray:
    """Write (T,N,d) float16 random unit latents to ``path`` a timestep at a time; return the memmap."""
    rng = np.random.default_rng(seed)
    out = np.lib.format.open_memmap(path, mode="w+", dtype=np.float16, shape=(T, N, d))
    for t in range(T):
        x = rng.standard_normal((N, d), dtype=np.float32)
        x /= np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)
        out[t] = x.astype(np.float16)
    out.flush()
    del out
    return np.load(path, mmap_mode="r")


def _time(fn, repeats: int) -> tuple[float, list[float], Any]:
    times, out = [], None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), times, out


def codebook_query_timings(workdir: Path, k: int, margin: float, repeats: int, threads: int,
                           rescore_share: float = 0.0, sample_count: int = 0) -> dict:
    """Codebook temporal queries in this (fresh) process: the stored codebook ``workdir/cb{k}`` over the
    latents memmap ``workdir/latents.npy``; returns the timings, re-scored latents and this process's
    peak RSS.

    The relevancy of random latents is nothing like a real query's (its codes crowd around 0.5 and
    R_avg), so with ``sample_count`` or ``rescore_share`` the queries are timed as lookups and the exact
    work a real field needs is timed on its own and added: ``sample_count`` Gaussians sampled uniformly
    for R_avg, and the re-scoring of ``rescore_share`` of all (t, g) pairs (whole codes picked at random,
    at every timestep: more scattered reads than the few timesteps a real query re-scores).
    """
    from fourlegs_engine.demo.simulated import SimulatedTextEncoder
    from fourlegs_engine.query.codebook import load_codebook

    torch.set_num_threads(threads)
    lat = np.load(workdir / "latents.npy", mmap_mode="r")
    T, N = int(lat.shape[0]), int(lat.shape[1])
    book = load_codebook(workdir / f"cb{k}", k, lat)
    if book is None:
        raise InputError(f"no codebook K={k} for these latents", file=workdir)
    forced_work = margin > 0 and (rescore_share > 0 or sample_count > 0)
    eng = QueryEngine(flat_scene(T, N), RandomField(lat), SimulatedTextEncoder(), QueryOptions(path="codebook", codebook_refine=0.0 if forced_work else margin), codebook=book)
    eng.reference_embeddings()
    t0 = time.perf_counter()
    eng.temporal(QUERY)
    cold = time.perf_counter() - t0
    texts = [f"{QUERY} {i}" for i in range(max(1, repeats))]
    t0 = time.perf_counter()
    for q in texts:  # text encoding is the encoder's cost, timed apart
        eng.embed_query(q)
    encode = (time.perf_counter() - t0) / len(texts)
    queries = iter(texts)
    anon = [resident_mb("RssAnon")]

    def query() -> None:
        eng.temporal(next(queries))
        anon.append(resident_mb("RssAnon"))

    warm, times, _ = _time(query, repeats)
    forced: dict[str, Any] = {}
    if forced_work:
        # the exact work reads scattered latents: time it with the field in the page cache, as a field
        # queried repeatedly is (every pass is in forced_rescore_times_s; new samples each pass)
        cache_s = warm_page_cache(workdir / "latents.npy")
        rng = np.random.default_rng(0)
        per_code = book.histogram.sum(axis=0, dtype=np.int64)
        held = np.nonzero(per_code)[0]
        order = rng.permutation(held)
        picked = order[:int(np.searchsorted(np.cumsum(per_code[order]), rescore_share * T * N)) + 1] \
            if rescore_share > 0 else order[:0]
        ts = np.arange(T)

        def exact_work() -> tuple[int, int]:
            sampled = eng.codebook_path.sample_members(QUERY, [held], [sample_count], ts, rng)[0][1].size if sample_count else 0
            rescored = eng.scorer.score_any(QUERY, eng.codebook_path.band_members(picked, ts, ts)[2]).size if picked.size else 0
            anon.append(resident_mb("RssAnon"))
            return sampled, rescored

        exact_s, exact_times, (sampled, rescored) = _time(exact_work, 5)
        forced = {"forced_rescore_share": rescore_share, "forced_rescored_latents": int(rescored),
                  "forced_sampled_latents": int(sampled), "forced_rescore_s": exact_s,
                  "forced_rescore_times_s": exact_times, "page_cache_warm_s": cache_s}
        warm += exact_s
    runs = len(texts) + 1
    return {"first_query_s": cold, "query_s": warm, "query_times_s": times, "text_encode_s": encode, **forced,
            "refine_margin": margin, "rescored_latents_per_query": int(eng.stats["rescored_latents"]) // runs,
            "sampled_latents_per_query": int(eng.stats["sampled_latents"]) // runs,
            "decoded_latents": int(eng.stats["decoded_latents"]), "peak_rss_mb": peak_rss_mb(),
            "anon_rss_mb": max(anon), "file_rss_mb": resident_mb("RssFile"), "rss_scope": "query process"}


def run_query_speed(*, gaussians: int, timesteps: int, codebook_sizes: list[int], repeats: int,
                    exact_timesteps: int, spatial_scene: str, workdir: Path, progress: bool = True,
                    refine_margins: Sequence[float] = (0.0,), rescore_share: float = 0.0,
                    sample_count: int = 0) -> dict:
    from fourlegs_engine.demo.simulated import SimulatedTextEncoder

    T, N = int(timesteps), int(gaussians)
    if T < 1 or N < 1:
        raise InputError("needs at least one timestep and one Gaussian", field="size")
    report: dict[str, Any] = {"benchmark": "query-speed", "num_gaussians": N, "num_timesteps": T, "latent_dim": 128,
                              "torch_threads": torch.get_num_threads(), "query": QUERY, "rows": []}
    t0 = time.perf_counter()
    lat = random_latents(workdir / "latents.npy", T, N)
    report["write_latents_s"] = time.perf_counter() - t0
    field = RandomField(lat)
    scene = flat_scene(T, N)
    text = SimulatedTextEncoder()
    import multiprocessing

    spawn = multiprocessing.get_context("spawn")
    for K in codebook_sizes:
        t0 = time.perf_counter()
        book = build_codebook(lat, K, out_dir=workdir / f"cb{K}", progress=progress)
        build = time.perf_counter() - t0
        levels = book.meta["levels"]
        del book
        for margin in refine_margins:
            share, count = (rescore_share, int(sample_count)) if margin > 0 else (0.0, 0)
            with spawn.Pool(1) as pool:
                row = pool.apply(codebook_query_timings, (workdir, K, margin, repeats, torch.get_num_threads(), share,
                                                          count))
            forced = [f"{count} sampled"] * (count > 0) + [f"{100 * share:g}% of the field re-scored"] * (share > 0)
            name = f"codebook K={K}" + (f" + exact re-scoring ±{margin:g}" if margin > 0 else "") + (
                f" (lookup + {' + '.join(forced)}, timed)" if forced else "")
            report["rows"].append({"path": name, "levels": levels, "build_s": build, **row})
            _print_row(report["rows"][-1])
    steps = T if exact_timesteps <= 0 else min(T, int(exact_timesteps))
    eng = QueryEngine(scene, field, text, QueryOptions.exact())
    eng.embed_query(QUERY)
    eng.reference_embeddings()
    t0 = time.perf_counter()
    for t in range(steps):
        eng.gaussian_relevancy(QUERY, t)
    per_t = (time.perf_counter() - t0) / steps
    row = {"path": "exact", "query_s": per_t * T, "timed_timesteps": steps,
           "extrapolated": steps < T, "seconds_per_timestep": per_t, "peak_rss_mb": peak_rss_mb(),
           "rss_scope": "whole benchmark process"}
    if steps == T:
        t0 = time.perf_counter()
        eng.temporal(QUERY)
        row["query_s"] = time.perf_counter() - t0
    report["rows"].append(row)
    _print_row(row)
    if spatial_scene != "none":
        report["spatial"] = _spatial_timings(spatial_scene, text, repeats, workdir)
        for r in report["spatial"]:
            print(f"  map {r['path']:5s} {r['width']}x{r['height']} N={r['num_gaussians']}: {r['seconds']:.3f} s",
                  file=sys.stderr)
    report["peak_rss_mb"] = peak_rss_mb()
    return report


def _spatial_timings(size: str, text, repeats: int, workdir: Path) -> list[dict]:
    from fourlegs_engine.demo.synthetic import ensure_demo_bundle
    from fourlegs_engine.scene.bundle import load_bundle

    scene = load_bundle(ensure_demo_bundle(size))
    lat = random_latents(workdir / "scene_latents.npy", scene.num_timesteps, scene.num_gaussians, seed=1)
    field = RandomField(lat)
    cam = scene.cameras.cameras(0, "all")[0]
    cam = cam.scaled(640 / cam.width)
    t = scene.num_timesteps // 2
    rows = []
    for path, fast in (("fast", True), ("exact", False)):
        eng = QueryEngine(scene, field, text, QueryOptions.exact(spatial="fast" if fast else "exact"))
        eng.relevancy_map(QUERY, cam, t)  # warm-up: text embeddings, background relevancy
        sec, times, maps = _time(lambda: eng.relevancy_map(QUERY, cam, t), max(1, min(repeats, 3)))
        rows.append({"path": path, "seconds": sec, "times_s": times, "width": cam.width, "height": cam.height,
                     "num_gaussians": scene.num_gaussians, "scene": size})
    return rows


def _print_row(row: dict) -> None:
    extra = f" (build {row['build_s']:.1f} s, first query {row['first_query_s']:.3f} s)" if "build_s" in row else ""
    extra += f" (extrapolated from {row['timed_timesteps']} timesteps)" if row.get("extrapolated") else ""
    print(f"  {row['path']:18s} temporal query {row['query_s']:.4f} s{extra}; peak RSS {row['peak_rss_mb']:.0f} MB",
          file=sys.stderr)


def markdown(report: dict) -> str:
    lines = ["Codebook rows: timed in a fresh process that opens the stored codebook (its peak RSS is the "
             "query's own); the exact row: in the benchmark process. Own memory: the largest anonymous "
             "resident memory (RssAnon) seen after each query; mapped file pages: resident pages of the "
             "memory-mapped latents and codebook (RssFile, shared with the page cache, which the kernel maps "
             "in around every touched page).", "",
             f"Temporal query over {report['num_gaussians']:,} Gaussians x {report['num_timesteps']} timesteps x "
             f"128-d latents (random, float16 memmap), torch threads {report['torch_threads']}", "",
             "| path | seconds per query | first query (s) | exact latents per query | codebook build (s) | "
             "peak RSS (MB) | own memory (MB) | mapped file pages (MB) |", "|---|---|---|---|---|---|---|---|"]
    for r in report["rows"]:
        q = f"{r['query_s']:.4f}" + (f" (extrapolated from {r['timed_timesteps']} timesteps)" if r.get("extrapolated") else "")
        rss = f"{r['peak_rss_mb']:.0f}" + (" (whole benchmark process)" if r.get("rss_scope", "").startswith("whole")
                                           else "")
        rescored = r.get("forced_rescored_latents", r.get("rescored_latents_per_query", ""))
        if r.get("forced_sampled_latents"):
            rescored = f"{r['forced_sampled_latents']} sampled + {rescored}"
        lines.append(f"| {r['path']} | {q} | {r.get('first_query_s', float('nan')):.3f} | "
                     f"{rescored} | {r.get('build_s', float('nan')):.1f} | {rss} | "
                     f"{_mb(r.get('anon_rss_mb'))} | {_mb(r.get('file_rss_mb'))} |")
    if report.get("tiled"):
        from .query_speed_tiled import markdown_rows
        lines += markdown_rows(report["tiled"])
    if report.get("spatial"):
        lines += ["", "| relevancy map | resolution | Gaussians | seconds |", "|---|---|---|---|"]
        for r in report["spatial"]:
            lines.append(f"| {r['path']} | {r['width']}x{r['height']} | {r['num_gaussians']:,} ({r['scene']}) | "
                         f"{r['seconds']:.3f} |")
    return "\n".join(lines)


def _mb(value: Any) -> str:
    return "" if value is None or value != value else f"{value:.0f}"


def run_query_speed_cli(args) -> int:
    if args.json and Path(args.json).exists() and not args.overwrite:
        raise OutputExistsError(args.json)
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        sizes = [int(v) for v in str(args.codebook).split(",") if v.strip()]
    except ValueError:
        raise InputError(f"expected comma-separated integers, got {args.codebook!r}", field="--codebook") from None
    try:
        margins = [float(v) for v in str(args.refine).split(",") if v.strip()] or [0.0]
    except ValueError:
        raise InputError(f"expected comma-separated numbers, got {args.refine!r}", field="--refine") from None
    workdir = Path(tempfile.mkdtemp(prefix="fourlegs-query-speed-"))
    try:
        report = run_query_speed(gaussians=args.gaussians, timesteps=args.timesteps, codebook_sizes=sizes,
                                 repeats=args.repeats, exact_timesteps=args.exact_timesteps,
                                 spatial_scene=args.spatial_scene, workdir=workdir, refine_margins=margins,
                                 rescore_share=args.rescore_share, sample_count=args.sample_count)
        if args.tiled_scene != "none":
            from .query_speed_tiled import run_tiled_query_speed
            shutil.rmtree(workdir, ignore_errors=True)  # the random field first: both need the disk space
            workdir.mkdir()
            report["tiled"] = run_tiled_query_speed(args.tiled_scene, gaussians=args.gaussians,
                                                    timesteps=args.timesteps, codebook_sizes=sizes,
                                                    margins=margins, workdir=workdir)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    print(markdown(report))
    if args.json:
        write_json_atomic(args.json, report, overwrite=args.overwrite)
        print(f"wrote {args.json}")
    return 0
