"""OpenCV <-> Blender camera conventions (pure numpy, no bpy).

OpenCV cameras look down +z with x right and y down; Blender cameras look down -z with x right and
y up. World coordinates are shared (our scenes use +z up, as Blender does), so only the camera frame
changes: ``c2w_blender = c2w_opencv @ diag(1, -1, -1, 1)`` (flip the camera's y and z axes).

Intrinsics map to Blender's camera data with ``sensor_fit='HORIZONTAL'``: the lens in millimetres is
``fx * sensor_width / width``; an off-centre principal point becomes ``shift_x/shift_y`` (in units of
the larger image side); ``fx != fy`` becomes the render's pixel aspect ratio.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FLIP_YZ = np.diag([1.0, -1.0, -1.0, 1.0])
DEFAULT_SENSOR_WIDTH_MM = 36.0


def opencv_to_blender_c2w(c2w: np.ndarray) -> np.ndarray:
    """(…,4,4) OpenCV camera-to-world -> Blender camera ``matrix_world`` (…,4,4)."""
    return np.asarray(c2w, dtype=np.float64) @ FLIP_YZ


def blender_to_opencv_c2w(matrix_world: np.ndarray) -> np.ndarray:
    """(…,4,4) Blender camera ``matrix_world`` -> OpenCV camera-to-world (…,4,4).

    Any scale in ``matrix_world`` is removed (Blender cameras may be scaled; a camera frame is not).
    """
    m = np.array(matrix_world, dtype=np.float64)
    rot = m[..., :3, :3]
    norms = np.linalg.norm(rot, axis=-2, keepdims=True)
    m[..., :3, :3] = rot / np.maximum(norms, 1e-300)
    return m @ FLIP_YZ


def rigid_inverse(m: np.ndarray) -> np.ndarray:
    """Inverse of a (4,4) rigid transform."""
    m = np.asarray(m, dtype=np.float64)
    out = np.eye(4)
    out[:3, :3] = m[:3, :3].T
    out[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return out


@dataclass(frozen=True)
class BlenderLens:
    """Blender camera-data values equivalent to a pinhole ``K`` at ``width x height`` pixels."""

    lens_mm: float
    sensor_width_mm: float
    shift_x: float
    shift_y: float
    pixel_aspect_x: float
    pixel_aspect_y: float


def intrinsics_to_blender(K: np.ndarray, width: int, height: int,
                          sensor_width_mm: float = DEFAULT_SENSOR_WIDTH_MM) -> BlenderLens:
    """(3,3) pixel intrinsics -> Blender lens/shift/pixel aspect (``sensor_fit='HORIZONTAL'``)."""
    K = np.asarray(K, dtype=np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    side = float(max(width, height))
    # Blender scales the frame by the pixel aspect; keep fx as the reference and express fy through it.
    aspect_y = fx / fy
    aspect_x = 1.0
    if aspect_y < 1.0:
        aspect_x, aspect_y = 1.0 / aspect_y, 1.0
    return BlenderLens(
        lens_mm=float(fx * sensor_width_mm / width),
        sensor_width_mm=float(sensor_width_mm),
        shift_x=float((width / 2.0 - cx) / side),
        shift_y=float((cy - height / 2.0) / side),
        pixel_aspect_x=float(aspect_x),
        pixel_aspect_y=float(aspect_y),
    )


def project_blender(points: np.ndarray, matrix_world: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points through a Blender-convention camera (looks down its local -z).

    Args:
        points: (M,3) world points.
        matrix_world: (4,4) Blender camera matrix (no scale).
        K: (3,3) pixel intrinsics (pixel rows counted downward, as in images).
    Returns:
        uv: (M,2) pixel coordinates, depth: (M,) distance along the viewing direction.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    w2c = rigid_inverse(matrix_world)
    cam = p @ w2c[:3, :3].T + w2c[:3, 3]  # Blender camera frame: x right, y up, -z forward
    depth = -cam[:, 2]
    safe = np.where(np.abs(depth) < 1e-12, 1e-12, depth)
    u = K[0, 0] * cam[:, 0] / safe + K[0, 2]
    v = -K[1, 1] * cam[:, 1] / safe + K[1, 2]
    return np.stack([u, v], axis=1), depth


def camera_intrinsics(lens_mm: float, sensor_width_mm: float, sensor_height_mm: float, sensor_fit: str,
                      width: int, height: int, *, shift_x: float = 0.0, shift_y: float = 0.0,
                      pixel_aspect_x: float = 1.0, pixel_aspect_y: float = 1.0) -> np.ndarray:
    """(3,3) pixel intrinsics of a Blender camera for any ``sensor_fit`` ('AUTO', 'HORIZONTAL', 'VERTICAL').

    AUTO applies ``sensor_width`` to the larger image side (Blender's rule); VERTICAL applies
    ``sensor_height`` to the image height.
    """
    # Blender fits the sensor to the frame after the pixel aspect stretches it.
    frame_w, frame_h = width * pixel_aspect_x, height * pixel_aspect_y
    fit = sensor_fit
    if fit == "AUTO":
        fit = "HORIZONTAL" if frame_w >= frame_h else "VERTICAL"
        sensor = sensor_width_mm
    else:
        sensor = sensor_width_mm if fit == "HORIZONTAL" else sensor_height_mm
    if not (lens_mm > 0 and sensor > 0 and width > 0 and height > 0):
        raise ValueError(f"need positive lens, sensor and size, got lens={lens_mm} sensor={sensor} "
                         f"size={width}x{height}")
    if fit == "HORIZONTAL":
        fx = lens_mm * width / sensor
        fy = fx * pixel_aspect_x / pixel_aspect_y
    else:
        fy = lens_mm * height / sensor
        fx = fy * pixel_aspect_y / pixel_aspect_x
    side = float(max(frame_w, frame_h))
    cx = width / 2.0 - shift_x * side / pixel_aspect_x
    cy = height / 2.0 + shift_y * side / pixel_aspect_y
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0,1] -> scene-linear (IEC 61966-2-1), float32; clamps to [0,1] first.

    Gaussian colours are display-referred (they were fitted to sRGB photographs); Blender works in
    scene-linear and encodes to sRGB on output, so linearizing here makes saved frames reproduce the
    rasterizer's colours exactly under the Standard view transform.
    """
    c = np.clip(np.nan_to_num(np.asarray(c, dtype=np.float32)), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)
