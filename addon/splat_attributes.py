"""Blender's own Gaussian-splat attributes (Blender 5.3+ ``GAUSSIAN_SPLAT`` point clouds), pure numpy.

The conventions are those Blender's PLY importer (``bpy.ops.wm.ply_import``) writes for an Inria 3DGS
file, read back from Blender itself (``tests/test_blender_native_splats.py`` holds us to it):

- ``position`` FLOAT_VECTOR: the centre;
- ``rotation`` QUATERNION: the unit quaternion (w, x, y, z);
- ``scale`` FLOAT_VECTOR: linear standard deviations, ``exp`` of the file's log scales;
- ``radiance:base`` FLOAT4: the SH DC coefficients (``f_dc_0..2``, not colours) and, as the fourth
  value, the opacity ``sigmoid(logit)``;
- ``radiance:sh_k`` FLOAT_VECTOR, k = 0 .. K-2: the k-th higher SH coefficient of red, green and blue
  (``f_rest_k``, ``f_rest_{k+M}``, ``f_rest_{k+2M}`` with M = K - 1), present only for SH degree >= 1.

A scene with RGB colours instead of SH gets DC coefficients ``(rgb - 0.5) / C0`` (degree 0).
"""
from __future__ import annotations

import math
from typing import Any, Optional

import numpy as np

SH_C0 = 0.28209479177387814
POSITION, ROTATION, SCALE, BASE = "position", "rotation", "scale", "radiance:base"
SH_PREFIX = "radiance:sh_"
#: attribute name -> (Blender data type, values per point)
KINDS = {POSITION: ("FLOAT_VECTOR", 3), ROTATION: ("QUATERNION", 4), SCALE: ("FLOAT_VECTOR", 3),
         BASE: ("FLOAT4", 4)}
SH_KIND = ("FLOAT_VECTOR", 3)


def sh_name(k: int) -> str:
    return f"{SH_PREFIX}{k}"


def sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.clip(np.asarray(x, np.float64), -60.0, 60.0)))


def unit_quaternions(q: np.ndarray) -> np.ndarray:
    """(N,4) w,x,y,z -> unit length (a zero quaternion becomes the identity)."""
    q = np.asarray(q, np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    out = np.where(norm > 1e-12, q / np.maximum(norm, 1e-300), np.array([1.0, 0.0, 0.0, 0.0]))
    return out.astype(np.float32)


def base_radiance(dc: np.ndarray, opacity_logits: np.ndarray) -> np.ndarray:
    """(N,3) SH DC coefficients and (N,) opacity logits -> (N,4) ``radiance:base``."""
    out = np.empty((len(opacity_logits), 4), np.float32)
    out[:, :3] = dc
    out[:, 3] = sigmoid(opacity_logits)
    return out


def splat_attributes(means: np.ndarray, rotations: np.ndarray, log_scales: np.ndarray, opacity_logits: np.ndarray,
                     *, colors: Optional[np.ndarray] = None, sh: Optional[np.ndarray] = None,
                     ) -> dict[str, np.ndarray]:
    """Blender's splat attributes of N Gaussians.

    Args:
        means: (N,3); rotations: (N,4) w,x,y,z; log_scales: (N,3); opacity_logits: (N,).
        colors: (N,3) RGB in [0,1] (used when ``sh`` is None).
        sh: (N,K,3) SH coefficients, DC first (K = 1, 4, 9 or 16).
    Returns:
        name -> float32 array of shape (N, values per point), in :data:`KINDS` / ``radiance:sh_k`` order.
    """
    out = {POSITION: np.ascontiguousarray(means, np.float32), ROTATION: unit_quaternions(rotations),
           SCALE: np.exp(np.clip(np.asarray(log_scales, np.float64), -30.0, 10.0)).astype(np.float32)}
    if sh is not None:
        sh = np.asarray(sh, np.float32)
        out[BASE] = base_radiance(sh[:, 0, :], opacity_logits)
        for k in range(sh.shape[1] - 1):
            out[sh_name(k)] = np.ascontiguousarray(sh[:, k + 1, :])
    else:
        dc = (np.asarray(colors, np.float64) - 0.5) / SH_C0
        out[BASE] = base_radiance(dc, opacity_logits)
    return out


def kind_of(name: str) -> tuple[str, int]:
    """(Blender data type, values per point) of a splat attribute name."""
    return SH_KIND if name.startswith(SH_PREFIX) else KINDS[name]


def blend_timestep(arr: Any, t: float) -> np.ndarray:
    """Row ``t`` of a (T,N,C) array, linearly interpolated for fractional ``t`` (clamped to the range)."""
    T = arr.shape[0]
    t = min(max(float(t), 0.0), float(T - 1))
    lo = int(math.floor(t))
    hi = min(lo + 1, T - 1)
    w = t - lo
    a = np.asarray(arr[lo], dtype=np.float32)
    if w < 1e-6 or hi == lo:
        return a
    return (1.0 - w) * a + w * np.asarray(arr[hi], dtype=np.float32)
