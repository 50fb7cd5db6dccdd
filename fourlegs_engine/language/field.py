"""``LanguageField``: the distilled 4D language field of a bundle, ready for querying.

Opens ``scene.json["language"]``: the (T, N, d) float16 latents (memory-mapped, never loaded whole)
and the autoencoder's decoder (a state dict read with ``torch.load(weights_only=True)``).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from ..errors import InputError
from ..fileio import load_npy, read_json
from .autoencoder import AE_REPORT, FeatureDecoder, load_decoder, weights_fingerprint
from .encoders import CANONICAL_PHRASES


FULL_FINITE_CHECK_BYTES = 64 << 20  # latents up to this size are checked whole when opened
SAMPLED_TIMESTEPS = 8
SAMPLED_ROWS = 4096


def check_field_matches_decoder(root: Path, lang: dict[str, Any], decoder: FeatureDecoder) -> None:
    """Refuse a field distilled with another autoencoder than the one now in the bundle.

    Fields record the decoder's :func:`weights_fingerprint`; older fields are compared through the
    autoencoder's config hash (``language.config.autoencoder`` vs ``autoencoder.json``).
    """
    decoder_file = root / str(lang["decoder"])
    fix = "run `fourlegs distill --overwrite` to distil the field again with the current autoencoder"
    recorded = lang.get("decoder_fingerprint")
    if recorded is not None:
        now = weights_fingerprint(decoder)
        if now != recorded:
            raise InputError(f"the language field was distilled with another autoencoder (decoder fingerprint "
                             f"{recorded}, {decoder_file.name} now {now}); {fix}", file=decoder_file)
        return
    config = lang.get("config")
    report = root / AE_REPORT
    if isinstance(config, dict) and config.get("autoencoder") and report.is_file():
        trained = read_json(report)
        now = trained.get("config_hash") if isinstance(trained, dict) else None
        if now is not None and now != config["autoencoder"]:
            raise InputError(f"the language field was distilled with another autoencoder (hash "
                             f"{config['autoencoder']}, {report.name} now {now}); {fix}", file=decoder_file)


def check_latents_finite(latents: np.ndarray, path: Path) -> None:
    """InputError naming ``path`` when latents hold NaN/Inf: checked whole for files up to
    ``FULL_FINITE_CHECK_BYTES``, else on evenly spaced rows of evenly spaced timesteps."""
    T = latents.shape[0]
    if latents.nbytes <= FULL_FINITE_CHECK_BYTES:
        steps, rows = range(T), slice(None)
    else:
        steps = sorted(set(np.linspace(0, T - 1, min(T, SAMPLED_TIMESTEPS)).astype(int).tolist()))
        rows = np.unique(np.linspace(0, latents.shape[1] - 1, min(latents.shape[1], SAMPLED_ROWS)).astype(int))
    for t in steps:
        block = np.asarray(latents[t][rows])
        if not np.isfinite(block).all():
            raise InputError(f"timestep {t} holds NaN or Inf latents; the field is damaged: run "
                             "`fourlegs distill --overwrite`", file=path, field="latents")


class LanguageField:
    """A distilled language field.

    Attributes:
        latents: (T, N, d) float16 memmap of per-Gaussian latents.
        encoder_name: the video-text encoder whose space the decoder maps back to.
        canonical_phrases: the LERF canonical phrases used for relevancy.
        latent_dim: d (128).
        mode: how the field was distilled ("lift", "optimize", "lift+refine").
        config_hash: identifies the settings that produced it.
    """

    def __init__(self, latents: np.ndarray, decoder: FeatureDecoder, *, encoder_name: str,
                 canonical_phrases: Sequence[str] = CANONICAL_PHRASES, mode: str = "", config_hash: str = "",
                 device: str | torch.device = "cpu"):
        if latents.ndim != 3:
            raise InputError(f"latents have shape {tuple(latents.shape)}, expected (T,N,d)", field="latents")
        if latents.shape[2] != decoder.dims[0]:
            raise InputError(f"latents have {latents.shape[2]} channels, the decoder expects {decoder.dims[0]}",
                             field="latents")
        self.latents = latents
        self.device = torch.device(device)
        self.decoder = decoder.to(self.device).eval()
        self.encoder_name = encoder_name
        self.canonical_phrases = tuple(canonical_phrases)
        self.mode = mode
        self.config_hash = config_hash

    @classmethod
    def open(cls, bundle: str | Path, *, latents: str | Path | None = None,
             device: str | torch.device = "cpu") -> "LanguageField":
        """Open the field of a bundle; ``latents`` picks another latents file (e.g. a benchmark mode's)."""
        root = Path(bundle)
        meta_path = root / "scene.json"
        meta = read_json(meta_path)
        lang = meta.get("language") if isinstance(meta, dict) else None
        if not lang:
            raise InputError("the scene has no distilled language field; run `fourlegs language` (extract, "
                             "train-ae, distill) first", file=meta_path, field="language")
        for key in ("decoder", "latents", "encoder"):
            if key not in lang:
                raise InputError("missing key", file=meta_path, field=f"language.{key}")
        from ..scene.bundle import is_inside
        for key in ("decoder", "latents"):
            if not isinstance(lang[key], str) or not is_inside(root.resolve(), lang[key]):
                raise InputError(f"{lang[key]!r} is not a file inside the bundle", file=meta_path,
                                 field=f"language.{key}")
        info = dict(lang)
        lat_path = root / lang["latents"]
        if latents is not None:
            lat_path = Path(latents)
            side = lat_path.with_name("latents.json")
            if side.is_file():
                info.update({k: v for k, v in read_json(side).items() if k in ("mode", "config_hash")})
        arr = load_npy(lat_path, mmap=True, field="language.latents")
        T, N = int(meta.get("num_timesteps", -1)), int(meta.get("num_gaussians", -1))
        if arr.ndim != 3 or tuple(arr.shape[:2]) != (T, N):
            raise InputError(f"has shape {tuple(arr.shape)}, expected (T={T}, N={N}, d)", file=lat_path,
                             field="latents")
        decoder = load_decoder(root / lang["decoder"])
        check_field_matches_decoder(root, lang, decoder)
        check_latents_finite(arr, lat_path)
        return cls(arr, decoder, encoder_name=str(info["encoder"]),
                   canonical_phrases=info.get("canonical_phrases") or CANONICAL_PHRASES,
                   mode=str(info.get("mode", "")), config_hash=str(info.get("config_hash", "")), device=device)

    # -------------------------------------------------------------------------------- access
    @property
    def latent_dim(self) -> int:
        return int(self.latents.shape[2])

    @property
    def feature_dim(self) -> int:
        return int(self.decoder.dims[-1])

    @property
    def num_timesteps(self) -> int:
        return int(self.latents.shape[0])

    @property
    def num_gaussians(self) -> int:
        return int(self.latents.shape[1])

    def latents_at(self, t: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """(N, d) latents of timestep t on the field's device."""
        if not 0 <= int(t) < self.num_timesteps:
            raise InputError(f"timestep {t} is out of range 0..{self.num_timesteps - 1}", field="t")
        return torch.from_numpy(np.array(self.latents[int(t)])).to(self.device, dtype)

    @torch.no_grad()
    def decode(self, latents: torch.Tensor | np.ndarray, chunk: int = 65536) -> torch.Tensor:
        """(M, d) latents (per Gaussian, or rendered per pixel) -> (M, D) L2-normalized features.

        Non-finite inputs are treated as zeros so no NaN leaves this function.
        """
        z = torch.as_tensor(np.asarray(latents) if isinstance(latents, np.ndarray) else latents)
        if z.dim() != 2 or z.shape[1] != self.latent_dim:
            raise InputError(f"latents have shape {tuple(z.shape)}, expected (M, {self.latent_dim})",
                             field="latents")
        z = torch.nan_to_num(z.to(self.device, torch.float32), nan=0.0, posinf=0.0, neginf=0.0)
        if z.shape[0] == 0:
            return z.new_zeros((0, self.feature_dim))
        return torch.cat([self.decoder(z[s:s + chunk]) for s in range(0, z.shape[0], chunk)])

    def describe(self) -> dict[str, Any]:
        return {"encoder": self.encoder_name, "latent_dim": self.latent_dim, "mode": self.mode,
                "num_timesteps": self.num_timesteps, "num_gaussians": self.num_gaussians,
                "canonical_phrases": list(self.canonical_phrases), "config_hash": self.config_hash}
