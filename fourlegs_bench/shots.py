"""``fourlegs bench shots SCENE "text"``: plan a highlight and measure how every frame shows its subject.

Writes, into ``--out``: ``plan.json``, ``quality.json`` (one record per frame and the per-shot
summary, :mod:`.shot_quality`), ``quality.md`` (the summary table) and ``contact.png`` (the engine's
contact sheet of the plan, masks included).

The subject comes from the scene's language field through the query engine (the product's path), or,
with ``--annotations REPORT`` (``fourlegs bench real-annotations``' report.json), from the capture's
annotation: the ball's triangulated centre per timestep gives its Gaussians (the foreground Gaussians
within the ball's radius), "the ball in the air" its in-the-air runs and "the ball" every timestep it
was found; "a person" is every other foreground Gaussian at every timestep (the people, two in the
basketball capture) — so the framing is measured apart from how well a field lifts the phrase.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np

BALL_PHRASES = ("the ball", "the ball in the air")
#: Phrases the annotation answers: the ball's, and "a person" (every foreground Gaussian that is not the
#: ball's, at every timestep: the capture's people, which the framing splits into instances).
ANNOTATED_PHRASES = BALL_PHRASES + ("a person",)
#: Gaussians fainter than this are not part of a person (the framing ignores them too).
MIN_OPACITY = 0.1
#: The ball's Gaussians: foreground Gaussians this far from its triangulated centre (its radius plus
#: the width of a splat).
BALL_REACH_M = 0.15


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    out, start = [], None
    for t, on in enumerate(list(flags) + [False]):
        if on and start is None:
            start = t
        elif not on and start is not None:
            out.append((start, t - 1))
            start = None
    return out


class AnnotatedBallLocalizer:
    """A localizer (``fourlegs_engine.highlights.Localizer``) answering from a real-annotations report."""

    def __init__(self, scene, report: dict[str, Any], phrase: str, *, reach_m: float = BALL_REACH_M):
        from fourlegs_engine.errors import InputError

        if phrase not in ANNOTATED_PHRASES:
            raise InputError(f"the annotation report answers {', '.join(map(repr, ANNOTATED_PHRASES))}, not "
                             f"{phrase!r}", field="text")
        self.scene, self.phrase, self.reach = scene, phrase, float(reach_m)
        steps = report["per_timestep"]
        self.centres = np.full((scene.num_timesteps, 3), np.nan)
        in_air = np.zeros(scene.num_timesteps, bool)
        for row in steps:
            t = int(row["t"])
            if 0 <= t < scene.num_timesteps and row.get("centre") is not None:
                self.centres[t] = row["centre"]
                in_air[t] = bool(row.get("in_air"))
        found = np.isfinite(self.centres).all(axis=1)
        self.positive = {"the ball in the air": found & in_air, "the ball": found}.get(phrase,
                                                                                    np.ones(len(found), bool))
        fg = scene.gaussians.foreground
        self.foreground = None if fg is None else np.asarray(fg, dtype=bool)
        if phrase == "a person" and self.foreground is None:
            raise InputError("the scene marks no foreground Gaussians, so 'a person' has no annotation",
                             field="foreground")
        opacity = 1.0 / (1.0 + np.exp(-np.asarray(scene.gaussians.opacity_logits, np.float64)))
        self.solid = opacity >= MIN_OPACITY

    def members(self, t: int) -> np.ndarray:
        """(N,) bool: the phrase's Gaussians at timestep ``t``: the ball's (none where the ball was not
        found), or for "a person" every solid foreground Gaussian that is not the ball's."""
        t = min(max(int(t), 0), self.scene.num_timesteps - 1)
        N = self.scene.num_gaussians
        ball = np.zeros(N, bool)
        if np.isfinite(self.centres[t]).all():
            d = np.linalg.norm(np.asarray(self.scene.gaussians.means[t], np.float64) - self.centres[t], axis=1)
            ball = d < self.reach
            ball = ball & self.foreground if self.foreground is not None else ball
        if self.phrase == "a person":
            return self.foreground & self.solid & ~ball
        return ball

    def gaussian_relevancy(self, query: str, t: int):
        """(N,) float32 tensor: 1 on the ball's Gaussians at ``t``."""
        import torch

        return torch.as_tensor(self.members(t).astype(np.float32))

    def relevancy_map(self, query: str, camera, t: int, fast: bool = False, outputs=("relevancy",)) -> dict:
        import torch
        from fourlegs_engine.render import render_frame

        g = self.scene.gaussians.at(min(max(int(t), 0), self.scene.num_timesteps - 1))
        with torch.no_grad():
            out = render_frame(g, camera, outputs=("features", "alpha"), features=self.gaussian_relevancy(query, t)[:, None])
        rel = out["features"][..., 0] / out["alpha"][..., 0].clamp_min(1e-3)
        return {"relevancy": rel.clamp(0, 1)}

    def temporal(self):
        from fourlegs_engine.query.results import TemporalResult

        runs = _runs(self.positive)
        scores = self.positive.astype(np.float64) / max(int(self.positive.sum()), 1)
        if not runs:
            return TemporalResult(scores, self.positive.copy(), [], None, None, False, f"{self.phrase!r} is never annotated")
        segment = max(runs, key=lambda r: (r[1] - r[0], r[0]))
        return TemporalResult(scores, self.positive.copy(), runs, segment, (segment[0] + segment[1]) // 2, True, "")

    def best_view(self, t: int) -> Optional[str]:
        """The training camera that sees the ball at ``t`` unoccluded (least occluded), in frame and nearest."""
        from .shot_quality import frame_quality

        cams = self.scene.cameras.cameras(min(t, self.scene.cameras.num_timesteps - 1), "train")
        subject = self.members(t)
        if not subject.any():
            return None
        g = self.scene.gaussians.at(t)
        best = None
        for i, cam in enumerate(cams):
            small = cam.scaled(0.5)
            q = frame_quality(g, subject, small)
            dist = float(np.linalg.norm(cam.center - self.centres[t]))
            key = (not q["in_frame"], round(q["occluded"], 2), dist)
            if best is None or key < best[0]:
                best = (key, cam.name or f"camera{i:02d}")
        return best[1]

    def localize(self, query: str, need: set[str]):
        from fourlegs_engine.query.results import Localization

        temporal = self.temporal()
        t = temporal.peak if temporal.found else 0
        best = self.best_view(t) if temporal.found and need & {"best_view", "action_centre"} else None
        centre = self.centres[t] if temporal.found and "action_centre" in need else None
        return Localization(query=query, scene=self.scene.name, temporal=temporal, best_view=best,
                            action_centre=centre, t=t)


def register_bench(bench_sub: Any) -> None:
    p = bench_sub.add_parser(
        "shots", help="plan a highlight and measure every frame's subject: height, centre offset, in frame, occlusion",
        description="Plans the highlight of TEXT in SCENE with a preset and measures, for every frame, the framed "
                    "subject's projected height (fraction of the frame height), its centre offset, whether it is "
                    "wholly in frame and how much of it is occluded; writes plan.json, quality.json, quality.md "
                    "and contact.png into --out.")
    p.add_argument("scene", help="the scene bundle")
    p.add_argument("text", help="the query")
    p.add_argument("--preset", default="broadcast", help="highlight preset (default broadcast)")
    p.add_argument("--resolution", default="640x360", help="plan resolution WxH (default 640x360)")
    p.add_argument("--width", type=int, default=320, help="width the frames are measured at (default 320)")
    p.add_argument("--annotations", default=None, metavar="REPORT",
                   help="take the subject from a `bench real-annotations` report.json instead of the language field")
    p.add_argument("-o", "--out", required=True, help="output folder")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from fourlegs_engine.errors import InputError

    try:
        width, height = (int(v) for v in str(args.resolution).lower().split("x"))
    except ValueError:
        raise InputError(f"must be WIDTHxHEIGHT, got {args.resolution!r}", field="--resolution") from None
    report = measure_shots(Path(args.scene), args.text, Path(args.out), preset=args.preset,
                           resolution=(width, height), width=args.width,
                           annotations=None if args.annotations is None else Path(args.annotations),
                           overwrite=args.overwrite)
    print(report["markdown"])
    for m in report["messages"]:
        print("  message:", m)
    return 0


def measure_shots(scene_path: Path, text: str, out: Path, *, preset: str = "broadcast",
                  resolution: tuple[int, int] = (640, 360), width: int = 320, annotations: Optional[Path] = None,
                  overwrite: bool = False) -> dict[str, Any]:
    """Plan, measure and write the outputs (see the module doc); returns the report written to quality.json."""
    from fourlegs_engine.errors import OutputExistsError
    from fourlegs_engine.fileio import read_json, write_json_atomic
    from fourlegs_engine.highlights.framing import scene_up
    from fourlegs_engine.highlights.planner import plan_highlight, subject_framing
    from fourlegs_engine.highlights.presets import load_preset
    from fourlegs_engine.highlights.preview import write_contact_sheet
    from fourlegs_engine.pipeline import open_query_engine, open_scene

    from .shot_quality import markdown_table, plan_quality, summarize

    if (out / "quality.json").exists() and not overwrite:
        raise OutputExistsError(f"{out / 'quality.json'} exists (use --overwrite)")
    out.mkdir(parents=True, exist_ok=True)
    scene = open_scene(str(scene_path))
    localizer = (AnnotatedBallLocalizer(scene, read_json(annotations), text) if annotations is not None
                 else open_query_engine(scene))
    start = time.process_time()
    plan = plan_highlight(scene, localizer, text, load_preset(preset), resolution=resolution)
    plan_cpu = time.process_time() - start
    plan.save(out / "plan.json", overwrite=True)
    up = scene_up(scene.cameras.cameras(0, "all"))
    found: dict[tuple[int, int], np.ndarray] = {}

    def subjects(k: int, t: int) -> np.ndarray:
        if (k, t) not in found:
            f = subject_framing(scene, localizer, text, t, up, [], instance=k)
            rel = localizer.gaussian_relevancy(text, t)
            found[k, t] = f.region.members if f is not None else np.asarray(rel.detach().cpu() if hasattr(rel, "detach") else rel) > 0.5
        return found[k, t]

    records = plan_quality(scene, plan, subjects, width=width)
    rows = summarize(records)
    write_contact_sheet(out / "contact.png", scene, plan, localizer=localizer, width=width, overwrite=True)
    report = {"scene": str(scene_path), "text": text, "preset": preset, "resolution": list(resolution),
              "measured_width": width, "subject_source": "annotations" if annotations else "language field",
              "localization": {k: plan.localization.get(k) for k in ("segment", "peak", "segments",
                                                                     "highlighted_segments", "best_view",
                                                                     "action_region", "instances")},
              "plan_cpu_s": plan_cpu, "messages": plan.messages, "summary": rows, "frames": records,
              "markdown": markdown_table(rows)}
    write_json_atomic(out / "quality.json", report, overwrite=True)
    (out / "quality.md").write_text(report["markdown"] + "\n", encoding="utf-8")
    return report
