"""The deterministic phrase space: 768-d unit embeddings of phrases, no network, the same on every machine.

Two teachers that are not video-text networks embed their phrases here: the simulated encoder of the
demo scenes (:mod:`fourlegs_engine.demo.simulated`) and the annotation masks
(:mod:`.annotations`). They share the orthonormal basis (a shared ``generic`` axis, one axis per known
lemma, one per canonical phrase) and :class:`PhraseEncoder`, their text side.

Lemma embeddings (:func:`lemma_embedding`)
    A phrase is reduced to lemmas (lower case, stop words dropped, synonyms and inflections mapped to
    one lemma: "jumps", "leaping" -> "jump"; "man", "player" -> "person"). Every known lemma owns one
    axis of a fixed orthonormal basis of R^768 (built once from a fixed seed); an unknown word gets a
    deterministic pseudo-random unit vector from a hash of the word (nearly orthogonal to everything).
    The phrase embedding is ``sqrt(g) * generic + sqrt(1-g) * normalize(sum_k w_k * v_k)`` with the
    shared ``generic`` axis (share ``g = GENERIC_SHARE`` = 0.3) and per-lemma weights ``w_k`` (the
    subject "person" weighs 0.35, objects of an action 0.5, the rest 1). Hence:

    * a query is closest to the label that uses its words (cosine 1 for the same lemmas),
    * labels sharing only the subject ("person jumping" vs "person waving") stay below the canonical
      phrases' similarity, so the LERF relevancy of one against the other is < 0.5,
    * the canonical phrases ("object", "things", "stuff", "texture") are mostly the generic axis
      (share ``CANONICAL_GENERIC_SHARE`` = 0.92): cosine ~ sqrt(0.3 * 0.92) = 0.525 to *every* phrase,
    * unrelated queries have cosine ~0.3 (the generic share) to every label: relevancy ~0.1.
"""
from __future__ import annotations

import hashlib
import math
import re
from functools import lru_cache
from typing import Sequence

import numpy as np
import torch

from ..errors import InputError
from .phrases import CANONICAL_PHRASES

EMBED_DIM = 768
GENERIC_SHARE = 0.3
CANONICAL_GENERIC_SHARE = 0.92
BASIS_SEED = 20250401
BACKGROUND_PHRASE = "background"

STOP_WORDS = frozenset("""a an the in on of at to into onto with by from for and or is are was were be being
his her their its this that these those some while up down it one who which as""".split())

# Inflections and synonyms -> lemma. Words of the synthetic label vocabulary, their common variants,
# and a few neighbours a user is likely to type.
LEMMAS: dict[str, str] = {}
_GROUPS = {
    "person": "person people persons man men woman women player players guy girl boy human someone somebody "
              "kid child athlete",
    "jump": "jump jumps jumping jumped leap leaps leaping hop hops hopping",
    "wave": "wave waves waving waved",
    "throw": "throw throws throwing threw thrown toss tosses tossing tossed pass passes passing",
    "catch": "catch catches catching caught",
    "walk": "walk walks walking walked stroll strolling",
    "hold": "hold holds holding held carry carries carrying grab grabbing",
    "stand": "stand stands standing stood idle",
    "ball": "ball balls basketball football",
    "fly": "fly flies flying flew airborne",
    "air": "air sky",
    "hand": "hand hands arm arms",
    "floor": "floor ground court",
    "wall": "wall walls dome",
    "box": "box boxes crate",
    "wood": "wooden wood",
    "bench": "bench benches seat",
    "background": "background",
}
for _lemma, _words in _GROUPS.items():
    for _w in _words.split():
        LEMMAS[_w] = _lemma
KNOWN_LEMMAS: tuple[str, ...] = tuple(_GROUPS)
LEMMA_WEIGHTS = {"person": 0.35, "ball": 0.5, "air": 0.5, "wood": 0.5}
GENERIC_AXIS = "<generic>"


def lemmatize(text: str) -> list[str]:
    """Lemmas of ``text`` in order (stop words dropped; unknown words kept, lightly stemmed)."""
    if not isinstance(text, str):
        raise InputError(f"text must be a string, got {type(text).__name__}", field="text")
    out = []
    for word in re.findall(r"[a-z0-9']+", text.lower()):
        word = word.strip("'")
        if not word or word in STOP_WORDS:
            continue
        if word in LEMMAS:
            out.append(LEMMAS[word])
            continue
        out.append(_stem(word))
    return out


def _stem(word: str) -> str:
    for suffix in ("ing", "ed", "es", "s"):
        if word.endswith(suffix) and len(word) - len(suffix) >= 3:
            stem = word[: -len(suffix)]
            return LEMMAS.get(stem, stem)
    return word


@lru_cache(maxsize=1)
def phrase_basis() -> dict[str, np.ndarray]:
    """Orthonormal axes (float64) for the generic direction, every known lemma and the canonical phrases."""
    names = (GENERIC_AXIS,) + KNOWN_LEMMAS + tuple(CANONICAL_PHRASES)
    rng = np.random.default_rng(BASIS_SEED)
    q, r = np.linalg.qr(rng.normal(size=(EMBED_DIM, len(names))))
    q = q * np.sign(np.diag(r))[None, :]  # make the factorization unique
    return {name: q[:, i].copy() for i, name in enumerate(names)}


@lru_cache(maxsize=4096)
def word_vector(lemma: str) -> np.ndarray:
    """(D,) float64 unit vector of a lemma: a basis axis when known, else a hash-seeded random direction."""
    basis = phrase_basis()
    if lemma in basis:
        return basis[lemma]
    digest = hashlib.sha256(("fourlegs-simulated:" + lemma).encode()).digest()
    v = np.random.default_rng(int.from_bytes(digest[:8], "little")).normal(size=EMBED_DIM)
    return v / np.linalg.norm(v)


def lemma_embedding(text: str) -> np.ndarray:
    """(D,) float64 unit embedding of one phrase from its lemmas (see the module docstring)."""
    basis = phrase_basis()
    stripped = text.strip().lower() if isinstance(text, str) else text
    if stripped in CANONICAL_PHRASES:
        e = math.sqrt(CANONICAL_GENERIC_SHARE) * basis[GENERIC_AXIS] + \
            math.sqrt(1 - CANONICAL_GENERIC_SHARE) * basis[stripped]
        return e / np.linalg.norm(e)
    content = np.zeros(EMBED_DIM)
    for lemma in dict.fromkeys(lemmatize(text)):  # each lemma once, in order
        content += LEMMA_WEIGHTS.get(lemma, 1.0) * word_vector(lemma)
    norm = np.linalg.norm(content)
    if norm < 1e-12:  # empty or stop words only: purely generic
        return basis[GENERIC_AXIS].copy()
    e = math.sqrt(GENERIC_SHARE) * basis[GENERIC_AXIS] + math.sqrt(1 - GENERIC_SHARE) * content / norm
    return e / np.linalg.norm(e)


class PhraseEncoder:
    """The text side of a teacher whose phrases live in this space: texts -> rows of :meth:`phrase_embedding`.

    Subclasses set ``phrase_embedding`` (str -> (768,) float64 unit vector) and ``name``.
    """

    dim = EMBED_DIM

    @staticmethod
    def phrase_embedding(text: str) -> np.ndarray:
        raise NotImplementedError

    def encode_text(self, texts: Sequence[str] | str) -> torch.Tensor:
        """n strings -> (n, 768) float32, L2-normalized; the same phrase always gives the same vector."""
        return torch.from_numpy(self.encode_text64(texts)).float()

    def encode_text64(self, texts: Sequence[str] | str) -> np.ndarray:
        """n strings -> (n, 768) float64 (for float64 references)."""
        texts = [texts] if isinstance(texts, str) else list(texts)
        return np.stack([self.phrase_embedding(t) for t in texts]) if texts else np.zeros((0, EMBED_DIM))
