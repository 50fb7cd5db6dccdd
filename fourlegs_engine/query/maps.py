"""Spatial relevancy maps of the query engine: per-pixel relevancy, depth and alpha from one camera.

Exact (paper §3.2): render the (N,d) latents, decode every pixel, score it. Fast: render the (N,1)
per-Gaussian relevancy; empty pixels take the exact path's background value, so
``map = Σ w_i R_i + (1 − alpha) R_bg``. ``resolution_scale`` renders at a fraction of the camera's size.

A fast map asked for ``relevant_only`` (what the best view's relevant mass needs) of a small subject (at
most ``REGION_MAX_SHARE`` of the Gaussians relevant) renders only the Gaussians that touch the box around
the relevant ones' footprints (R > 0.5, α ≥ alpha_min): inside the
box every pixel is blended from the same Gaussians in the same order as in the full map, and outside it
no relevant Gaussian reaches, so the map is at most 0.5 there in both (when R_bg ≤ 0.5) and
``max(R − 0.5, 0)`` is the full map's everywhere.
"""
from __future__ import annotations

import threading
from collections import Counter
from typing import Any, Callable, Iterable, Optional, Sequence

import numpy as np
import torch

from ..errors import InputError
from ..render import RasterOptions, rasterize
from ..render.kernel_projection import numba as _numba, project_gaussians_fused
from ..render.projection import project_gaussians
from ..scene.camera import Camera
from ..scene.scene import Scene
from . import spatial
from .results import CentreResult
from .scoring import LatentScorer

MAP_OUTPUTS = ("relevancy", "depth", "alpha")
RELEVANT = 0.5
#: pixels added on each side of the relevant Gaussians' box (projection implementations round bounds
#: differently by at most a pixel)
REGION_PAD = 2
#: a relevant-only map renders the relevant region alone when at most this share of the Gaussians is
#: relevant (a small subject); a larger subject's box holds most of the frame, and finding it costs a
#: projection of every Gaussian more than it saves
REGION_MAX_SHARE = 0.1


class SpatialMaps:
    """Relevancy maps of a scene's field (see the module docstring).

    Args:
        scene: the scene (geometry per timestep).
        scorer: scores rendered latents (exact maps) and gives the background relevancy.
        gaussian_relevancy_many: ``(queries, t) -> (N,Q)`` per-Gaussian relevancy (fast maps).
        fast: the default path (``QueryOptions.spatial == "fast"``).
        resolution_scale: default fraction of each camera's resolution.
        render_options / render_backend: passed to the rasterizer.
        stats: the engine's counters (``render_relevancy``, ``render_features``, ``decoded_pixels``).
    """

    def __init__(self, scene: Scene, scorer: LatentScorer,
                 gaussian_relevancy_many: Callable[[list[str], int], torch.Tensor], *, fast: bool,
                 resolution_scale: float, render_options: Any, render_backend: str, stats: Counter):
        self.scene = scene
        self.scorer = scorer
        self.gaussian_relevancy_many = gaussian_relevancy_many
        self.fast = bool(fast)
        self.resolution_scale = float(resolution_scale)
        self.render_options = render_options
        self.render_backend = render_backend
        self.stats = stats
        self._stats_lock = threading.Lock()  # fast maps of several views may be rendered concurrently

    def _count(self, key: str) -> None:
        with self._stats_lock:
            self.stats[key] += 1

    def camera(self, camera: Camera, scale: Optional[float]) -> Camera:
        """``camera`` at the map resolution (``scale``, default :attr:`resolution_scale`)."""
        s = self.resolution_scale if scale is None else float(scale)
        return camera if s == 1.0 else camera.scaled(s)

    def rasterize(self, t: int, camera: Camera, features: torch.Tensor, outputs: tuple[str, ...],
                  subset: Optional[torch.Tensor] = None) -> dict:
        """The scene at ``t`` (its Gaussians in ``subset`` (N,) bool, default all) rendered with their
        per-Gaussian ``features`` (N,C), or (M,C) for the subset's M."""
        frame = self.scene.gaussians.at(t)
        g = (frame.means, frame.rotations, frame.log_scales, frame.opacity_logits)
        if subset is not None:
            g = tuple(x[subset] for x in g)
        with torch.inference_mode():
            return rasterize(*g, camera, features=features, outputs=outputs, options=self.render_options,
                             backend=self.render_backend)

    def touching_relevant(self, t: int, camera: Camera, relevant: torch.Tensor) -> torch.Tensor:
        """(N,) bool: the Gaussians whose footprint touches the box (padded by ``REGION_PAD``) around the
        footprints of the ``relevant`` (N,) bool ones seen from ``camera`` at ``t`` (none when no relevant
        Gaussian is in view)."""
        frame = self.scene.gaussians.at(t)
        options = self.render_options or RasterOptions()
        project = project_gaussians_fused if _numba is not None and frame.means.device.type == "cpu" \
            else project_gaussians
        with torch.inference_mode():
            proj = project(frame.means, frame.rotations, frame.log_scales, frame.opacity_logits, camera, options,
                           torch.float32)
        seen = proj.visible & relevant.to(proj.visible.device)
        if not bool(seen.any()):
            return torch.zeros_like(proj.visible)
        b = proj.bounds
        x0, x1 = int(b[seen, 0].min()) - REGION_PAD, int(b[seen, 1].max()) + REGION_PAD
        y0, y1 = int(b[seen, 2].min()) - REGION_PAD, int(b[seen, 3].max()) + REGION_PAD
        return proj.visible & (b[:, 1] >= x0) & (b[:, 0] <= x1) & (b[:, 3] >= y0) & (b[:, 2] <= y1)

    def relevancy_maps(self, queries: Sequence[str], camera: Camera, t: int, fast: Optional[bool] = None,
                       outputs: Iterable[str] = MAP_OUTPUTS, *, scale: Optional[float] = None,
                       relevant_only: bool = False) -> dict[str, np.ndarray]:
        """Maps of several queries with one render and one per-pixel decode (``relevant_only``: fast maps
        whose values above 0.5 are the full map's and the rest at most 0.5, see the module docstring;
        ignored on the exact path and where R_bg > 0.5).

        Returns:
            "relevancy" (Q,H,W), "depth" (H,W), "alpha" (H,W) float32 (the requested ones).
        """
        t = self.scene.gaussians.check_timestep(t)
        outputs = tuple(outputs)
        unknown = set(outputs) - set(MAP_OUTPUTS)
        if unknown:
            raise InputError(f"unknown map outputs {sorted(unknown)} (relevancy, depth, alpha)", field="outputs")
        fast = self.fast if fast is None else bool(fast)
        cam = self.camera(camera, scale)
        H, W, Q = cam.height, cam.width, len(queries)
        qs = torch.stack([self.scorer.embed_query(q) for q in queries]) if Q else torch.zeros(0)
        r_bg = torch.tensor([self.scorer.background_relevancy(q) for q in queries], dtype=torch.float32)
        if self.scene.num_gaussians == 0:
            empty = {"relevancy": r_bg[:, None, None].expand(Q, H, W).numpy().copy(),
                     "depth": np.zeros((H, W), np.float32), "alpha": np.zeros((H, W), np.float32)}
            return {k: empty[k] for k in outputs}
        render_outputs = ("features", "alpha") + (("depth",) if "depth" in outputs else ())
        if fast:
            per_gaussian = self.gaussian_relevancy_many(list(queries), t)
            subset = None
            relevant = (per_gaussian > RELEVANT).any(dim=1) if Q else None
            if relevant_only and Q and bool((r_bg <= RELEVANT).all()) and \
                    float(relevant.float().mean()) <= REGION_MAX_SHARE:
                subset = self.touching_relevant(t, cam, relevant)
                self._count("relevant_only_maps")
            if subset is not None and not bool(subset.any()):   # nothing relevant in view: the background
                out = {"features": r_bg.new_zeros(H * W, Q), "alpha": r_bg.new_zeros(H, W),
                       "depth": r_bg.new_zeros(H, W)}
            else:
                out = self.rasterize(t, cam, per_gaussian if subset is None else per_gaussian[subset],
                                     render_outputs, subset)
            self._count("render_relevancy")
            alpha = out["alpha"].reshape(H, W)
            rel = out["features"].reshape(H, W, Q).permute(2, 0, 1) + \
                (1.0 - alpha).clamp(0.0, 1.0)[None] * r_bg[:, None, None]
        else:
            lat = torch.from_numpy(self.scorer.read_latents(t).astype(np.float32, copy=False))
            out = self.rasterize(t, cam, lat, render_outputs)
            self.stats["render_features"] += 1
            rel = self._decode_pixels(out["features"].reshape(H * W, -1), qs).reshape(Q, H, W)
            alpha = out["alpha"].reshape(H, W)
        result = {"relevancy": rel.clamp(0.0, 1.0), "alpha": alpha}
        if "depth" in outputs:
            result["depth"] = out["depth"].reshape(H, W)
        return {k: np.nan_to_num(result[k].detach().cpu().numpy().astype(np.float32)) for k in outputs}

    def _decode_pixels(self, pix: torch.Tensor, qs: torch.Tensor) -> torch.Tensor:
        """(P,d) rendered latents, (Q,D) queries -> (Q,P) relevancy. Pixels no Gaussian covers render the
        zero latent: it is decoded once (its row's result does not depend on the batch), every other pixel
        in chunks."""
        Q, chunk = qs.shape[0], self.scorer.chunk
        covered = torch.nonzero(pix.any(dim=1)).flatten()
        # a fresh (not inference-mode) tensor even when the expansion is already contiguous (a 1-pixel map)
        rel = self.scorer.score_latents_many(torch.zeros(1, pix.shape[1]), qs).T.expand(Q, pix.shape[0]).clone(
            memory_format=torch.contiguous_format)
        for s in range(0, covered.numel(), chunk):
            rows = covered[s:s + chunk]
            rel[:, rows] = self.scorer.score_latents_many(pix[rows], qs).T
        self.stats["decoded_pixels"] += covered.numel() + 1
        return rel

    def action_centre(self, maps: dict[str, np.ndarray], camera: Camera, t: int) -> CentreResult:
        """2D centre of mass of the best relevant component of a relevancy map (``maps`` at :meth:`camera`'s
        resolution of ``camera``; see :func:`.spatial.action_focus`), lifted to 3D with the rendered depth;
        plus that component's box, in ``camera``'s pixels (the centre lies inside it)."""
        cam = self.camera(camera, None)
        focus, box = spatial.action_focus(maps["relevancy"])
        centre = spatial.centre_of_mass(focus)
        point, depth = spatial.lift_centre(cam, centre, maps["depth"], maps["alpha"], focus)
        message = "" if point is not None else "no rendered surface under the relevant pixels; no 3D centre"
        scale = cam.width / camera.width
        return CentreResult(centre_px=None if centre is None else centre / scale, centre_3d=point, depth=depth,
                            bbox=None if box is None else _scale_box(box, scale), camera=camera.name, t=t,
                            message=message)


def _scale_box(box: tuple[int, int, int, int], scale: float) -> tuple[int, int, int, int]:
    if scale == 1.0:
        return box
    x0, y0, x1, y1 = box
    return (int(np.floor(x0 / scale)), int(np.floor(y0 / scale)), int(np.ceil((x1 + 1) / scale)) - 1,
            int(np.ceil((y1 + 1) / scale)) - 1)
