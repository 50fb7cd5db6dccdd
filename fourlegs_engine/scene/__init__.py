"""Scene data model, loaders, the native bundle format and validation."""
from .camera import Camera, CameraRig, look_rotation
from .gaussians import GaussianFrame, GaussianSequence, normalize_quaternions, quaternion_to_matrix
from .scene import Scene
from .bundle import is_bundle, load_bundle, write_bundle
from .loaders import load_scene

__all__ = ["Camera", "CameraRig", "GaussianFrame", "GaussianSequence", "Scene", "is_bundle", "load_bundle", "load_scene",
           "look_rotation", "normalize_quaternions", "quaternion_to_matrix", "write_bundle"]
