"""Small, exact stand-ins for a distilled field and a text encoder (query tests only).

``LinearField`` decodes latents with a fixed linear map followed by L2 normalization (the real
decoder's last step), so relevancy values can be computed independently in float64.
"""
from __future__ import annotations

import numpy as np
import torch

CANON = ("object", "things", "stuff", "texture")


class TableTextEncoder:
    """encode_text from a fixed table {phrase: (D,) vector}; unknown phrases get a seeded vector."""

    name = "table"

    def __init__(self, table: dict[str, np.ndarray], dim: int):
        self.table = {k: np.asarray(v, dtype=np.float64) for k, v in table.items()}
        self.dim = dim
        self.calls = 0

    def encode_text(self, texts):
        self.calls += 1
        out = []
        for text in texts:
            v = self.table.get(text)
            if v is None:
                v = np.random.default_rng(abs(hash(text)) % (2 ** 32)).normal(size=self.dim)
            out.append(v / max(np.linalg.norm(v), 1e-12))
        return torch.tensor(np.stack(out), dtype=torch.float32)


class LinearField:
    """``.latents`` (T,N,d); ``.decode`` = L2-normalize(latents @ W) with W (d,D)."""

    encoder_name = "table"
    canonical_phrases = CANON

    def __init__(self, latents: np.ndarray, weight: np.ndarray):
        self.latents = latents
        self.weight = torch.tensor(weight, dtype=torch.float32)

    def decode(self, x: torch.Tensor) -> torch.Tensor:
        y = torch.as_tensor(x, dtype=torch.float32) @ self.weight
        return y / y.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    def decode64(self, x: np.ndarray) -> np.ndarray:
        y = np.asarray(x, dtype=np.float64) @ self.weight.double().numpy()
        return y / np.maximum(np.linalg.norm(y, axis=-1, keepdims=True), 1e-12)


def orthonormal_setup(d: int = 8, D: int = 16, seed: int = 0):
    """Canonical phrases and two queries on orthonormal directions of R^D; W maps latent axis i to them.

    Returns (encoder, W (d,D), directions (D,D) orthonormal rows).
    """
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(D, D)))
    dirs = Q.T
    table = {c: dirs[i] for i, c in enumerate(CANON)}
    table["a ball flying"] = dirs[4]
    table["a person jumping"] = dirs[5]
    W = np.zeros((d, D))
    for i in range(min(d, D)):
        W[i] = dirs[i]
    return TableTextEncoder(table, D), W, dirs
