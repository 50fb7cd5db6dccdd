"""Options of the query engine (a plain dataclass, like :class:`~fourlegs_engine.render.RasterOptions`)."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Optional, Sequence

#: K of the codebook path
DEFAULT_CODEBOOK_SIZE = 4096
#: exact scores sampled per query to correct the codebook's R_avg (``codebook_refine`` > 0)
R_AVG_SAMPLES = 4096
#: the multiplier of LERF's pairwise softmax relevancy
RELEVANCY_SCALE = 10.0
MAX_CODEBOOK_SIZE = 1 << 20
MAX_RESOLUTION_SCALE = 8.0  # of the camera resolution; Camera.scaled also bounds the image size
MAX_TIMESTEP_ARGUMENT = 1 << 20  # strides and dilation radii beyond any scene's length


@dataclass(frozen=True)
class QueryOptions:
    """How :class:`~fourlegs_engine.query.engine.QueryEngine` answers a query.

    Attributes:
        path: "exact" or "codebook" (per-Gaussian relevancy and temporal localization).
        codebook_size: K of the codebook path.
        codebook_refine: margin of the codebook path's exact re-scoring (0: lookup only): R_avg is corrected
            by exact scores of ``codebook_samples`` sampled Gaussians, and at every timestep whose decision
            (s_t > 1/T) depends on them the Gaussians of the codes within this distance of R_avg are
            decoded exactly (see :func:`~fourlegs_engine.query.temporal.counts_from_codes_refined`); a row
            whose relevancy is certainly on one side of every threshold used gets a bound instead of the
            full decode (see :meth:`~fourlegs_engine.query.head.RelevancyHead.relevancy_windowed`).
        codebook_samples: exact scores spent on R_avg per query with ``codebook_refine`` > 0.
        negatives: scene-specific negative phrases added to the canonical set.
        temporal_stride: score every k-th timestep.
        spatial: "exact" (128-channel render, per-pixel decode) or "fast" (1-channel relevancy render).
        resolution_scale: render spatial maps at this fraction of each camera's resolution.
        dilation: radius of the temporal dilation.
        chunk: latents decoded per batch on the exact path.
        latent_dtype: read latents as this numpy dtype before decoding (e.g. "float16" to measure
            half-precision storage); None keeps the stored dtype.
        camera_split: which cameras ``best_view`` considers by default ("train", "test" or "all").
        render_options / render_backend: passed to the rasterizer.
        relevancy_scale: the temperature of the pairwise softmax relevancy.
    """

    path: str = "exact"
    codebook_size: int = DEFAULT_CODEBOOK_SIZE
    codebook_refine: float = 0.0
    codebook_samples: int = R_AVG_SAMPLES
    negatives: Sequence[str] = ()
    temporal_stride: int = 1
    spatial: str = "exact"
    resolution_scale: float = 1.0
    dilation: int = 1
    chunk: int = 32768
    latent_dtype: Optional[str] = None
    camera_split: str = "all"
    render_options: Any = None
    render_backend: str = "auto"
    relevancy_scale: float = RELEVANCY_SCALE

    def replace(self, **changes: Any) -> "QueryOptions":
        """A copy with ``changes`` applied."""
        return replace(self, **changes)
