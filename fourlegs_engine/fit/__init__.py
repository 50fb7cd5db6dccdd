"""Fit dynamic 3D Gaussians to a calibrated multiview video (``fourlegs fit``)."""
from ..lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "Capture": "dataset", "FitEvent": "options", "FitOptions": "options", "fit_capture": "fitter"
})
