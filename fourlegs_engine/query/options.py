"""Options of the query engine (a plain dataclass, like :class:`~fourlegs_engine.render.RasterOptions`)."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Optional, Sequence

#: K of the codebook path
DEFAULT_CODEBOOK_SIZE = 4096
#: the default path's exact re-scoring margin around R_avg (codes of K=4096)
DEFAULT_CODEBOOK_REFINE = 0.05
#: the best-view search scores every camera at this fraction of the map resolution ...
DEFAULT_VIEW_SCALE = 0.25
#: ... then re-scores this many of the best at the map resolution
DEFAULT_VIEW_CONFIRM = 3
#: exact scores sampled per query to correct the codebook's R_avg (``codebook_refine`` > 0)
R_AVG_SAMPLES = 4096
#: the rank of the sketch path's per-pair sketch
DEFAULT_SKETCH_RANK = 32
#: the multiplier of LERF's pairwise softmax relevancy
RELEVANCY_SCALE = 10.0
MAX_CODEBOOK_SIZE = 1 << 20
MAX_SKETCH_RANK = 512
#: the query engine's paths (see :class:`QueryOptions`)
QUERY_PATHS = ("exact", "codebook", "sketch")
MAX_RESOLUTION_SCALE = 8.0  # of the camera resolution; Camera.scaled also bounds the image size
MAX_TIMESTEP_ARGUMENT = 1 << 20  # strides and dilation radii beyond any scene's length


@dataclass(frozen=True)
class QueryOptions:
    """How :class:`~fourlegs_engine.query.engine.QueryEngine` answers a query.

    The defaults are the interactive path: the per-pair sketch (built once per field and stored beside it)
    with exact scoring where a temporal decision depends on it, fast 1-channel maps, and the best view
    scored at reduced resolution then confirmed. :meth:`exact` is the paper's path everywhere.

    Attributes:
        path: "exact", "codebook" or "sketch" (temporal localization; per-Gaussian relevancy is the
            codebook's on the codebook path, exact on the others). "sketch" decides every pair from a
            per-pair sketch of the relevancy head, stored beside the field, and scores exactly the pairs
            it leaves open (see :mod:`~fourlegs_engine.query.sketch_path`); a field whose decoder has no
            such head uses the codebook path.
        codebook_size: K of the codebook path.
        codebook_refine: margin of the codebook path's exact re-scoring (0: lookup only): R_avg is corrected
            by exact scores of ``codebook_samples`` sampled Gaussians, and at every timestep whose decision
            (s_t > 1/T) depends on them the Gaussians of the codes within this distance of R_avg are
            decoded exactly (see :func:`~fourlegs_engine.query.refined_counts.counts_from_codes_refined`); a row
            whose relevancy is certainly on one side of every threshold used gets a bound instead of the
            full decode (see :meth:`~fourlegs_engine.query.head.RelevancyHead.relevancy_windowed`).
        codebook_samples: exact scores spent on R_avg per query with ``codebook_refine`` > 0 (the sketch
            path spends as many).
        sketch_rank: the rank of the sketch path's per-pair sketch.
        negatives: scene-specific negative phrases added to the canonical set.
        temporal_stride: score every k-th timestep.
        spatial: "exact" (128-channel render, per-pixel decode) or "fast" (1-channel relevancy render).
        resolution_scale: render spatial maps at this fraction of each camera's resolution.
        view_scale: the best-view search scores every camera's map at this fraction of the map resolution
            (1: every camera at the map resolution) ...
        view_confirm: ... and re-scores the ``view_confirm`` best of them at the map resolution; the best
            of those is the best view.
        view_score: what ranks the views: "relevant" (the mass of relevancy above 0.5, which follows a
            small subject) or "mean" (the paper's mean relevancy, which the background's relevancy decides
            when the subject is small); see :mod:`~fourlegs_engine.query.viewpoint`.
        dilation: radius of the temporal dilation.
        chunk: latents decoded per batch on the exact path.
        latent_dtype: read latents as this numpy dtype before decoding (e.g. "float16" to measure
            half-precision storage); None keeps the stored dtype.
        camera_split: which cameras ``best_view`` considers by default ("train", "test" or "all").
        render_options / render_backend: passed to the rasterizer.
        relevancy_scale: the temperature of the pairwise softmax relevancy.
    """

    path: str = "sketch"
    codebook_size: int = DEFAULT_CODEBOOK_SIZE
    codebook_refine: float = DEFAULT_CODEBOOK_REFINE
    codebook_samples: int = R_AVG_SAMPLES
    sketch_rank: int = DEFAULT_SKETCH_RANK
    negatives: Sequence[str] = ()
    temporal_stride: int = 1
    spatial: str = "fast"
    resolution_scale: float = 1.0
    view_scale: float = DEFAULT_VIEW_SCALE
    view_confirm: int = DEFAULT_VIEW_CONFIRM
    view_score: str = "relevant"
    dilation: int = 1
    chunk: int = 32768
    latent_dtype: Optional[str] = None
    camera_split: str = "all"
    render_options: Any = None
    render_backend: str = "auto"
    relevancy_scale: float = RELEVANCY_SCALE

    @classmethod
    def exact(cls, **changes: Any) -> "QueryOptions":
        """The paper's path everywhere: every latent decoded, 128-channel maps, every view at full size."""
        return cls(**{"path": "exact", "spatial": "exact", "view_scale": 1.0, **changes})

    def replace(self, **changes: Any) -> "QueryOptions":
        """A copy with ``changes`` applied."""
        return replace(self, **changes)
