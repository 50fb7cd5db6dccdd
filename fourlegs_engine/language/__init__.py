"""Language field: video-text teacher features, the per-scene autoencoder and per-Gaussian latents.

- :mod:`.encoders` — the ``VideoTextEncoder`` protocol and the encoder registry (``get_encoder``).
- :mod:`.extract` — crop-pyramid teacher features per timestep (``extract_features``).
- :mod:`.skipping`, :mod:`.budget` — the cost knobs of extraction, and the plan that prices them before the
  work (``ExtractPlan``, ``estimate_plan``).
- :mod:`.autoencoder` — the 768 -> 128 feature autoencoder (``train_autoencoder``).
- :mod:`.distill` — per-Gaussian latents by lifting or optimizing (``distill_scene``).
- :mod:`.field` — :class:`LanguageField`, a distilled field opened from a bundle.
- :mod:`.simulated`, :mod:`.viclip` — the encoders (simulated for synthetic scenes, ViCLIP).
"""
from .autoencoder import AETrainConfig, train_autoencoder
from .budget import ExtractPlan, PlanEstimate, estimate_plan
from .distill import DistillConfig, distill_scene
from .encoders import VideoTextEncoder, encoder_names, get_encoder, register_encoder
from .extract import ExtractConfig, extract_features
from .field import LanguageField
from .phrases import CANONICAL_PHRASES

__all__ = ["AETrainConfig", "CANONICAL_PHRASES", "DistillConfig", "ExtractConfig", "ExtractPlan", "LanguageField",
           "PlanEstimate", "VideoTextEncoder", "distill_scene", "encoder_names", "estimate_plan", "extract_features",
           "get_encoder", "register_encoder", "train_autoencoder"]
