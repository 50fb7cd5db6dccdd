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


def two_cluster_scene(T: int = 4, n_per: int = 60, active=(1, 2), d: int = 8, D: int = 16, seed: int = 0,
                      size: tuple[int, int] = (48, 32)):
    """Two blobs of Gaussians: A at x=+0.6 ("a ball flying" at ``active`` timesteps, else "object"),
    B at x=-0.6 (always "object"). Camera "wide" sees both; camera "close" looks at A from near by.

    Returns (scene, field, encoder, dirs).
    """
    from fourlegs_engine.scene import Camera, CameraRig, GaussianSequence, Scene

    enc, W, dirs = orthonormal_setup(d, D, seed)
    rng = np.random.default_rng(seed)
    N = 2 * n_per
    base = np.concatenate([rng.normal(scale=0.12, size=(n_per, 3)) + [0.6, 0, 0],
                           rng.normal(scale=0.12, size=(n_per, 3)) + [-0.6, 0, 0]]).astype(np.float32)
    means = np.repeat(base[None], T, 0)
    rot = np.zeros((T, N, 4), np.float32)
    rot[..., 0] = 1
    g = GaussianSequence(means=means, rotations=rot, log_scales=np.full((N, 3), np.log(0.08), np.float32),
                         opacity_logits=np.full(N, 4.0, np.float32), colors=np.full((N, 3), 0.5, np.float32))
    lat = np.zeros((T, N, d), np.float32)
    lat[:, :, 0] = 1.0  # "object"
    wiggle = rng.uniform(0.0, 0.5, size=n_per)
    for t in active:
        lat[t, :n_per] = 0
        lat[t, :n_per, 4] = 1.0
        lat[t, :n_per, 6] = wiggle
    lat /= np.linalg.norm(lat, axis=-1, keepdims=True)
    w, h = size
    wide = Camera.look_at((0, -4, 0), (0, 0, 0), width=w, height=h, fov_y=0.6, name="wide")
    close = Camera.look_at((0.6, -1.6, 0), (0.6, 0, 0), width=w, height=h, fov_y=0.6, name="close")
    scene = Scene(gaussians=g, cameras=CameraRig.static([wide, close], [], T), name="clusters")
    return scene, LinearField(lat.astype(np.float16), W), enc, dirs
