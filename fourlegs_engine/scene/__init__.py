"""Scene data model, loaders, the native bundle format and validation."""
from ..lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "Camera": "camera", "CameraRig": "camera", "look_rotation": "camera", "GaussianFrame": "gaussians",
    "GaussianSequence": "gaussians", "normalize_quaternions": "gaussians", "quaternion_to_matrix": "gaussians",
    "Scene": "scene", "is_bundle": "bundle", "load_bundle": "bundle", "write_bundle": "bundle",
    "load_scene": "loaders"
})
