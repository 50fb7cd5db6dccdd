"""Query engine: when and where a text query happens in a scene with a distilled 4D language field.

``lerf`` (the LERF relevancy, stable form), ``temporal`` (paper §3.2 / supplementary A.2), ``spatial`` (centre of
mass, 3D lift, best component box), ``viewpoint`` (best view), ``codebook`` (k-means fast path),
``multiscene`` (§6.2), and :class:`~.engine.QueryEngine` tying them to a scene and its field, configured
by :class:`~.options.QueryOptions`.
"""
from ..lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "QueryEngine": "engine", "QueryOptions": "options", "relevancy": "lerf", "CentreResult": "results",
    "Localization": "results", "TemporalResult": "results", "ViewResult": "results"
})
