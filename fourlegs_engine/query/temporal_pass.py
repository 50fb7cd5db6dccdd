"""The exact temporal pass of the query engine: every Gaussian's relevancy at every scored timestep.

Latents are decoded one timestep at a time (never T x N x 768 at once), for all queries together, on
concurrent streams on the CPU. The per-Gaussian scores are kept (up to :data:`TEMPORAL_SCORE_BYTES`) so
later per-timestep lookups (fast maps, desaturation frames) reuse them instead of decoding again.
"""
from __future__ import annotations

import threading
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Optional, Sequence

import numpy as np
import torch

from ..threads import torch_threads
from .scoring import LatentScorer
from .temporal import counts_from_relevancy

TEMPORAL_SCORE_BYTES = 512 << 20  # exact temporal scores (T·N float32 per query) kept for per-frame reuse
TEMPORAL_STREAMS = 2  # timesteps scored concurrently on the exact temporal path (CPU)


class ExactTemporalPass:
    """Counts of relevant Gaussians per scored timestep by decoding every latent (``path="exact"``).

    ``stats`` is the engine's counters (``decoded_latents``).
    """

    def __init__(self, scorer: LatentScorer, num_gaussians: int, stats: Counter):
        self.scorer = scorer
        self.num_gaussians = int(num_gaussians)
        self.stats = stats
        # per-Gaussian scores already computed: query -> {t: (N,) row}
        self._scores: dict[str, dict[int, np.ndarray]] = {}

    def counts(self, queries: Sequence[str], timesteps: np.ndarray,
               report: Callable[[float, str], None]) -> list[tuple[np.ndarray, float, int]]:
        """Per query: relevant-Gaussian counts (S,) at ``timesteps``, R_avg and the number of relevant pairs.
        ``report(fraction, stage)`` is called before each timestep (it may raise to stop the pass)."""
        N, S, Q = self.num_gaussians, len(timesteps), len(queries)
        qs = torch.stack([self.scorer.embed_query(q) for q in queries])
        self.scorer.reference_embeddings()  # encoded here, not by two streams at once
        scores = np.empty((Q, S, N), dtype=np.float32)
        bookkeeping = threading.Lock()  # progress in start order and the decode count, across streams
        started = [0]

        def score_timestep(i: int) -> None:
            with bookkeeping:
                report(started[0] / S, "scoring timesteps")
                started[0] += 1
            lat = self.scorer.read_latents(int(timesteps[i]))
            chunk = self.scorer.chunk
            for s in range(0, N, chunk):
                scores[:, i, s:s + chunk] = self.scorer.score_latents_many(lat[s:s + chunk], qs).T.numpy()
            with bookkeeping:
                self.stats["decoded_latents"] += N

        self._for_each_timestep(score_timestep, S)
        per_query = S * N * 4
        for j, q in enumerate(queries if per_query <= TEMPORAL_SCORE_BYTES else []):
            self._scores.pop(q, None)
            self._scores[q] = {int(t): scores[j, i] for i, t in enumerate(timesteps)}
            while len(self._scores) * per_query > TEMPORAL_SCORE_BYTES:
                self._scores.pop(next(iter(self._scores)))
        return [(*counts_from_relevancy(scores[j]), np.zeros(len(timesteps), dtype=bool)) for j in range(Q)]

    def scores_at(self, query: str, t: int) -> Optional[np.ndarray]:
        """(N,) scores of ``query`` at ``t`` if a pass computed them, else None."""
        return self._scores.get(query, {}).get(int(t))

    def forget(self, query: str) -> None:
        """Drop the scores kept for ``query``."""
        self._scores.pop(query, None)

    def _for_each_timestep(self, work: Callable[[int], None], count: int) -> None:
        """Run ``work(i)`` for i in range(count). On the CPU with two or more torch threads the
        timesteps run on :data:`TEMPORAL_STREAMS` concurrent streams of fewer torch threads each: a
        timestep's scoring is a few large products between many elementwise tensor ops, which one
        stream on two threads spends largely at thread barriers. Each timestep's result is computed
        alone, so it is the same whichever stream runs it."""
        threads = torch.get_num_threads()
        head = self.scorer.head
        on_cpu = head is None or head.device.type == "cpu"
        streams = min(TEMPORAL_STREAMS, threads, count)
        if not on_cpu or streams < 2:
            for i in range(count):
                work(i)
            return
        stop = threading.Event()  # after a failure (or a cancel raised by work) the queued timesteps are skipped

        def guarded(i: int) -> None:
            if stop.is_set():
                return
            try:
                work(i)
            except BaseException:
                stop.set()
                raise

        with torch_threads(max(1, threads // streams)), ThreadPoolExecutor(streams) as pool:
            list(pool.map(guarded, range(count)))
