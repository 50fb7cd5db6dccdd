"""Relevancy of latents to text queries: the one place the query engine's paths decode and score.

:class:`LatentScorer` embeds the query and reference phrases (cached) and scores latents exactly,
through the field's :class:`~.head.RelevancyHead` when its decoder has one (relevancy straight from the
latents), else ``field.decode`` followed by the LERF relevancy (:mod:`.lerf`). The temporal pass, the
codebook path and the spatial maps all score through it, so they count their work in one ``stats``.
"""
from __future__ import annotations

from collections import Counter
from typing import Any, Optional, Sequence

import numpy as np
import torch

from .head import RelevancyHead
from .lerf import as_tensor, l2_normalize, reference_set, relevancy, relevancy_many
from .rows import RowReader
from ..errors import InputError


class LatentScorer:
    """Exact relevancy of a field's latents (per Gaussian or rendered per pixel) to text queries.

    Args:
        field: the distilled field (``.latents`` (T,N,d), ``.decode(M,d)->(M,D)``, ``.canonical_phrases``,
            optionally ``.decoder``).
        text_encoder: ``encode_text(list[str]) -> (n,D)`` of the encoder the field was distilled from.
        negatives: scene-specific negative phrases added to the canonical ones.
        relevancy_scale: the temperature of the pairwise softmax relevancy.
        chunk: latents decoded per batch.
        latent_dtype: numpy dtype latents are read as before decoding (None: float32).
        stats: the engine's counters (``encode_text``, ``decoded_latents``, ``bounded_latents``).
    """

    def __init__(self, field: Any, text_encoder: Any, *, negatives: Sequence[str], relevancy_scale: float,
                 chunk: int, latent_dtype: Optional[np.dtype], stats: Counter):
        self.field = field
        self.text_encoder = text_encoder
        self.negatives = tuple(str(n) for n in negatives if str(n).strip())
        self.relevancy_scale = float(relevancy_scale)
        self.chunk = int(chunk)
        self.latent_dtype = latent_dtype
        self.stats = stats
        self._text_cache: dict[str, torch.Tensor] = {}
        self._refs: Optional[tuple[torch.Tensor, Optional[torch.Tensor]]] = None
        self._head: Any = None  # RelevancyHead, False when the decoder has none, None before the first use
        self._row_reader: Optional[RowReader] = None
        self._background_score: dict[str, float] = {}

    @property
    def latents(self) -> Any:
        """(T,N,d) latents of the field (usually a memory map)."""
        return self.field.latents

    # ------------------------------------------------------------------ embeddings
    def encode(self, texts: list[str]) -> torch.Tensor:
        """(n,D) L2-normalized embeddings of ``texts`` (each encoded once per scorer)."""
        missing = [t for t in texts if t not in self._text_cache]
        if missing:
            self.stats["encode_text"] += 1
            with torch.inference_mode():
                emb = as_tensor(self.text_encoder.encode_text(missing))
            for text, e in zip(missing, emb):
                self._text_cache[text] = l2_normalize(e)
        return torch.stack([self._text_cache[t] for t in texts]) if texts else torch.zeros(0)

    def embed_query(self, query: str) -> torch.Tensor:
        """(D,) L2-normalized embedding of ``query`` (cached)."""
        if not isinstance(query, str) or not query.strip():
            raise InputError("the query text is empty", field="query")
        return self.encode([query])[0]

    def reference_embeddings(self) -> tuple[torch.Tensor, Optional[torch.Tensor]]:
        """Canonical (K,D) and negative (J,D)|None phrase embeddings."""
        if self._refs is None:
            canon = list(getattr(self.field, "canonical_phrases", None) or ())
            if not canon:
                from ..language.phrases import CANONICAL_PHRASES
                canon = list(CANONICAL_PHRASES)
            c = self.encode(canon)
            n = self.encode(list(self.negatives)) if self.negatives else None
            self._refs = (c, n)
        return self._refs

    def references(self) -> torch.Tensor:
        """(K+J,D) the canonical and negative phrases together."""
        canon, neg = self.reference_embeddings()
        return reference_set(canon, neg)

    # ------------------------------------------------------------------ decoding and scoring
    def read_latents(self, t: int) -> np.ndarray:
        """(N,d) latents of timestep ``t`` in the scoring dtype."""
        return np.asarray(self.latents[t], dtype=self.latent_dtype or np.float32)

    def decode(self, latents: np.ndarray | torch.Tensor) -> torch.Tensor:
        """(M,d) latents -> (M,D) decoded features, float32."""
        x = torch.as_tensor(latents)
        if x.dtype != torch.float32:
            x = x.to(torch.float32)
        with torch.inference_mode():
            out = self.field.decode(x)
        return as_tensor(out)

    @property
    def head(self) -> Optional[RelevancyHead]:
        """Relevancy straight from latents (None when the field's decoder has no such form)."""
        if self._head is None:
            self._head = RelevancyHead.from_decoder(getattr(self.field, "decoder", None)) or False
        return self._head or None

    def score_features(self, features: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
        """(M,D) decoded features, (D,) unit query -> (M,) relevancy."""
        canon, neg = self.reference_embeddings()
        return relevancy(features, q, canon, neg, scale=self.relevancy_scale)

    def score_latents_many(self, latents: np.ndarray | torch.Tensor, qs: torch.Tensor) -> torch.Tensor:
        """(M,d) latents (per Gaussian or rendered per pixel), (Q,D) unit queries -> (M,Q) relevancy of
        their decoded features; one chunk (at most ``self.chunk`` rows) at a time by the caller."""
        head = self.head
        if head is None:
            return relevancy_many(self.decode(latents), qs, self.references(), scale=self.relevancy_scale)
        with torch.inference_mode():
            return head.relevancy_many(torch.as_tensor(latents), qs, self.references(),
                                       scale=self.relevancy_scale).cpu()

    def score_latents(self, latents: np.ndarray, q: torch.Tensor,
                      window: Optional[tuple[float, float]] = None) -> torch.Tensor:
        """(M,d) latents -> (M,) relevancy, decoded in chunks of ``self.chunk``.

        With a ``window`` (low, high) a row whose relevancy is certainly outside it may get a bound instead
        that compares with every threshold in the window as its relevancy does (see
        :meth:`RelevancyHead.relevancy_windowed`; counted in ``stats["bounded_latents"]``)."""
        M = latents.shape[0]
        out = torch.empty(M, dtype=torch.float32)
        head = self.head if window is not None else None
        refs = self.references() if head is not None else None
        for s in range(0, M, self.chunk):
            if head is None:
                out[s:s + self.chunk] = self.score_latents_many(latents[s:s + self.chunk], q[None])[:, 0]
                continue
            with torch.inference_mode():
                values, exact = head.relevancy_windowed(torch.as_tensor(latents[s:s + self.chunk]), q, refs,
                                                        scale=self.relevancy_scale, window=window)
            out[s:s + self.chunk] = values.cpu()
            self.stats["bounded_latents"] += int((~exact).sum())
        self.stats["decoded_latents"] += M
        return out

    # ------------------------------------------------------------------ scattered rows
    def rows(self) -> RowReader:
        """Reader of scattered latent rows (``os.pread`` on a memory-mapped field: see :mod:`.rows`)."""
        if self._row_reader is None:
            self._row_reader = RowReader(self.latents)
        return self._row_reader

    def score_pairs(self, query: str, flat: np.ndarray, window: Optional[tuple[float, float]] = None) -> np.ndarray:
        """(M,) float64 exact relevancy of the Gaussians at sorted flat indices t*N+g (``window``: see
        :meth:`score_latents`)."""
        lat = self.rows().read(flat, dtype=self.latent_dtype or np.float32)
        if lat.shape[0] == 0:
            return np.zeros(0, dtype=np.float64)
        return self.score_latents(lat, self.embed_query(query), window).double().numpy()

    def score_any(self, query: str, flat: np.ndarray, window: Optional[tuple[float, float]] = None) -> np.ndarray:
        """(M,) float64 exact relevancy of the Gaussians at flat indices t*N+g, in any order (with a
        ``window``: bounds where certainly outside it, see :meth:`score_latents`)."""
        flat = np.asarray(flat, dtype=np.int64)
        order = np.argsort(flat, kind="stable")  # reads in file order
        scores = np.empty(flat.shape[0], dtype=np.float64)
        scores[order] = self.score_pairs(query, flat[order], window)
        return scores

    def score_any_rows(self, query: str, flat: np.ndarray, window: Optional[tuple[float, float]] = None
                       ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`score_any` and the (M,d) float32 latents it scored, both in the order of ``flat``."""
        flat = np.asarray(flat, dtype=np.int64)
        order = np.argsort(flat, kind="stable")  # reads in file order
        lat = self.rows().read(flat[order], dtype=self.latent_dtype or np.float32)
        scores = np.empty(flat.shape[0], dtype=np.float64)
        latents = np.empty((flat.shape[0], int(self.latents.shape[-1])), dtype=np.float32)
        if flat.size:
            scores[order] = self.score_latents(lat, self.embed_query(query), window).double().numpy()
            latents[order] = lat
        return scores, latents

    def background_relevancy(self, query: str) -> float:
        """Relevancy of an empty pixel on the exact path (its rendered latent is 0)."""
        if query not in self._background_score:
            d = int(self.latents.shape[-1])
            self._background_score[query] = float(
                self.score_features(self.decode(torch.zeros(1, d)), self.embed_query(query))[0])
        return self._background_score[query]

    def forget(self, query: str) -> None:
        """Drop the scores cached for ``query`` (its embedding stays)."""
        self._background_score.pop(query, None)
