"""Query engine: when and where a text query happens in a scene with a distilled 4D language field.

``relevancy`` (LERF form, stable), ``temporal`` (paper §3.2 / supplementary A.2), ``spatial`` (centre of
mass, 3D lift, best component box), ``viewpoint`` (best view), ``codebook`` (k-means fast path),
``multiscene`` (§6.2), and :class:`~.engine.QueryEngine` tying them to a scene and its field, configured
by :class:`~.options.QueryOptions`.
"""
from .engine import QueryEngine
from .options import QueryOptions
from .relevancy import relevancy
from .results import CentreResult, Localization, TemporalResult, ViewResult

__all__ = ["CentreResult", "Localization", "QueryEngine", "QueryOptions", "TemporalResult", "ViewResult",
           "relevancy"]
