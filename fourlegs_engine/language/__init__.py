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
from ..lazy import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "AETrainOptions": "autoencoder", "train_autoencoder": "autoencoder", "DistillOptions": "distill",
    "distill_scene": "distill", "VideoTextEncoder": "encoders", "encoder_names": "encoders",
    "get_encoder": "encoders", "register_encoder": "encoders", "ExtractOptions": "extract",
    "extract_features": "extract", "LanguageField": "field", "CANONICAL_PHRASES": "phrases",
    "ExtractPlan": "plans", "PlanEstimate": "budget", "estimate_plan": "budget"
})
