"""The demo: synthetic scenes with exact space-time ground truth and the simulated video-text encoder that
reads their labels. Fixtures for ``--demo``, the tests and the benchmarks, not the product's path.

- :mod:`.synthetic` — :func:`generate_scene`, :func:`ensure_demo_bundle` (the ``--demo`` scene, cached).
- :mod:`.parts`, :mod:`.script` — the scene's Gaussian parts and its scripted actions and labels.
- :mod:`.simulated` — the simulated encoder (:mod:`.simulated_kernels`: its numba kernels).

Importing this package registers the encoder name ``"simulated"``
(:func:`fourlegs_engine.language.encoders.get_encoder`); product packages import it only where the demo is
explicitly asked for (the pipeline's ``demo=`` path and its synthetic scenes, the commands).
"""
from typing import Any

from ..language.encoders import encoder_names, register_encoder
from ..lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    **{name: "synthetic" for name in ("QUERIES_FILE", "SIZES", "bundle_digest", "demo_bundle_path",
                                      "ensure_demo_bundle", "generate_scene", "read_queries",
                                      "write_synthetic_bundle")},
    **{name: "script" for name in ("LABELS", "QUERIES", "SCRIPT")},
    **{name: "simulated" for name in ("SimulatedTextEncoder", "SimulatedVideoEncoder", "create_encoder")},
})


def _simulated_encoder(**kwargs: Any) -> Any:
    """``get_encoder("simulated", labels= or scene=, ...)``: :func:`.simulated.create_encoder`."""
    from .simulated import create_encoder
    return create_encoder(**kwargs)


if "simulated" not in encoder_names():
    register_encoder("simulated", _simulated_encoder)
