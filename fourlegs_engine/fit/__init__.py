"""Fit dynamic 3D Gaussians to a calibrated multiview video (``fourlegs fit``)."""
from .dataset import Capture
from .fitter import FitEvent, FitOptions, fit_capture

__all__ = ["Capture", "FitEvent", "FitOptions", "fit_capture"]
