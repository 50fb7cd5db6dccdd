"""Gaussian rasterization: EWA projection, tile binning, front-to-back blending, any channel count.

Public API::

    rasterize(means, rotations, log_scales, opacity_logits, camera, *, colors=None, features=None,
              background=None, feature_background=None, outputs=("rgb",), options=None, backend="auto")
    render_frame(frame, camera, outputs=("rgb",), features=None, **kw)
    splat(means, rotations, log_scales, opacity_logits, camera, pixel_values, options=None)  # render's transpose

See :func:`rasterize` for shapes. ``reference`` holds the straightforward dense implementation used as
the speed/accuracy baseline.
"""
from ..lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "rasterize": "api", "render_frame": "api", "splat": "api", "RasterOptions": "options", "BlendWeights": "options",
    "OUTPUT_NAMES": "options", "cpu_kernels": None
})
