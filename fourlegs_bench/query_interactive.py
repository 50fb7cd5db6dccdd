"""``fourlegs bench query-interactive SCENE``: the default query path against the exact one on one scene.

For a bundle with a language field: the one-time index build (the default path's: the per-pair sketch, or
the codebook for a field without a relevancy head; stored beside the field), then
each query on the default path twice in one engine (its first and a later answer, the panel's case), then
the same queries on the exact path; per query the segments, peak and best view of both paths and whether
they agree. Seconds are wall and CPU (``time.process_time``) of this process: on a shared machine the CPU
seconds are the figure to read.
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Optional, Sequence

NEEDS = ("temporal", "best_view", "action_centre")


class _Clock:
    """Wall and CPU seconds of a block."""

    def __enter__(self) -> "_Clock":
        self.wall0, self.cpu0 = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.wall = round(time.perf_counter() - self.wall0, 3)
        self.cpu = round(time.process_time() - self.cpu0, 3)


def _answer(loc: Any) -> dict[str, Any]:
    tmp = loc.temporal
    return {"segments": [list(s) for s in tmp.segments], "segment": list(tmp.segment) if tmp.segment else None,
            "peak": tmp.peak, "best_view": loc.best_view,
            "centre_px": None if loc.centre_px is None else [round(float(v), 2) for v in loc.centre_px],
            "bbox": None if loc.bbox is None else list(loc.bbox)}


def run_query_interactive(bundle: str, queries: Sequence[str], *, exact: bool = True, rebuild_index: bool = False,
                          out: Optional[str] = None) -> dict[str, Any]:
    """Measure the default path (index build, first and later answer per query) and compare with the exact
    path; returns (and with ``out`` writes) the report."""
    from fourlegs_engine.fileio import write_json_atomic
    from fourlegs_engine.pipeline import QueryOptions, open_query_engine, text_encoder
    from fourlegs_engine.scene.bundle import load_bundle

    scene = load_bundle(Path(bundle))
    encoder = text_encoder(scene)
    options = QueryOptions()
    language_dir = Path(scene.root) / "language"
    if rebuild_index:
        for name in (f"codebook_{options.codebook_size}.npz", f"codes_{options.codebook_size}.npy",
                     f"members_{options.codebook_size}.npy", f"sketch_{options.sketch_rank}.npz",
                     f"sketch_coords_{options.sketch_rank}.npy", f"sketch_scalars_{options.sketch_rank}.npy"):
            (language_dir / name).unlink(missing_ok=True)
    report: dict[str, Any] = {"scene": str(bundle), "T": scene.num_timesteps, "N": scene.num_gaussians,
                              "options": {"path": options.path, "sketch_rank": options.sketch_rank,
                                          "codebook_size": options.codebook_size,
                                          "codebook_refine": options.codebook_refine, "spatial": options.spatial,
                                          "view_scale": options.view_scale, "view_confirm": options.view_confirm},
                              "queries": {}}
    with _Clock() as c:
        engine = open_query_engine(scene, encoder, options=options)
        engine.load_index()
    report["index_s"], report["index_cpu_s"] = c.wall, c.cpu
    for q in queries:
        row: dict[str, Any] = {}
        for which in ("first", "later"):
            with _Clock() as c:
                loc = engine.localize(q, NEEDS)
            row[f"{which}_s"], row[f"{which}_cpu_s"] = c.wall, c.cpu
            if which == "first":
                row["default"] = _answer(loc)
                row["default_timings"] = {k: round(v, 3) for k, v in loc.timings.items()}
                engine.forget_query(q)
        print(f"{q!r}: first {row['first_s']:.2f} s ({row['first_cpu_s']:.2f} CPU s), later {row['later_s']:.2f} s "
              f"({row['later_cpu_s']:.2f} CPU s); {row['default']}", flush=True)
        report["queries"][q] = row
    if exact:
        exact_engine = open_query_engine(scene, encoder, options=QueryOptions.exact(spatial=options.spatial))
        with _Clock() as c:
            results = exact_engine.temporal_many(list(queries))
        report["exact_temporal_s"], report["exact_temporal_cpu_s"] = c.wall, c.cpu
        for q, tmp in zip(queries, results):
            row = report["queries"][q]
            loc = exact_engine.localize(q, {"best_view", "action_centre"}, t=tmp.peak) if tmp.found else None
            row["exact"] = {"segments": [list(s) for s in tmp.segments],
                            "segment": list(tmp.segment) if tmp.segment else None, "peak": tmp.peak,
                            "best_view": None if loc is None else loc.best_view}
            row["same_segments_and_peak"] = (row["exact"]["segments"] == row["default"]["segments"]
                                             and row["exact"]["peak"] == row["default"]["peak"])
            row["same_best_view"] = row["exact"]["best_view"] == row["default"]["best_view"]
            print(f"{q!r}: exact {row['exact']}; same segments and peak: {row['same_segments_and_peak']}, "
                  f"same best view: {row['same_best_view']}", flush=True)
    if out:
        write_json_atomic(out, report, overwrite=True)
        print(f"wrote {out}")
    else:
        print(json.dumps(report, indent=1))
    return report
