"""CLIP's byte-level BPE tokenizer, reading the merge list ``bpe_simple_vocab_16e6.txt.gz``.

File format: a gzip'd UTF-8 text whose first line is a header (``#version: ...``) and whose further
lines are merges, two space-separated symbols each, in priority order. The vocabulary is built the
way CLIP builds it: the 256 byte symbols, the same 256 with the end-of-word marker ``</w>``, one
symbol per merge (at most 49152 - 256 - 2 merges are read), then ``<|startoftext|>`` and
``<|endoftext|>``. With the published file that is 49408 ids, end-of-text being the largest.

Text is cleaned as CLIP does (``ftfy.fix_text`` when ftfy is installed, else Unicode NFC; HTML
entities unescaped twice; whitespace runs collapsed; lower-cased) and split into pre-tokens with
CLIP's pattern: the special tokens, the contractions 's 't 're 've 'm 'll 'd, runs of letters (Unicode
category L*), single digits/numerals (category N*), and runs of anything else that is not whitespace.
The pattern is implemented as a small scanner over Unicode categories, so the ``regex`` package is
not needed; the tests check it against the official pattern run by ``regex`` (categories follow the
Unicode version of the running Python).
"""
from __future__ import annotations

import gzip
import html
import re
import unicodedata
from functools import lru_cache
from pathlib import Path

import torch

from ...errors import InputError

START_OF_TEXT = "<|startoftext|>"
END_OF_TEXT = "<|endoftext|>"
END_OF_WORD = "</w>"
MAX_MERGES = 49152 - 256 - 2
#: a vocabulary file that unpacks to more text than this is refused before it fills memory (the published one
#: unpacks to a few MB)
MAX_VOCAB_BYTES = 16 << 20
DEFAULT_CONTEXT_LENGTH = 32  # ViCLIP's text context (CLIP uses 77)
_CONTRACTIONS = ("'s", "'t", "'re", "'ve", "'m", "'ll", "'d")
# CLIP's \s (the regex package: Unicode White_Space) differs from Python's str.isspace() only by the
# four information separators U+001C..U+001F, which Python also counts as whitespace.
_SEPARATORS = "\x1c\x1d\x1e\x1f"
_WHITESPACE_RUN = re.compile(r"[^\S\x1c-\x1f]+")
# Matched by none of the pattern's classes under IGNORECASE (it case-folds to a letter without being
# one), so CLIP's findall skips it: U+0345 COMBINING GREEK YPOGEGRAMMENI.
_SKIPPED = "\u0345"


@lru_cache()
def bytes_to_unicode() -> dict[int, str]:
    """The reversible byte -> printable character table of GPT-2/CLIP BPE.

    Printable Latin-1 bytes map to themselves; the 68 others (controls, space, ...) map to
    characters 256, 257, ... in byte order, so every byte string has a whitespace-free spelling.
    Dictionary order is the vocabulary order of the 256 base symbols.
    """
    printable = (list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1))
                 + list(range(ord("®"), ord("ÿ") + 1)))
    table = {b: chr(b) for b in printable}
    extra = 0
    for b in range(256):
        if b not in table:
            table[b] = chr(256 + extra)
            extra += 1
    return table


def _category(char: str) -> str:
    """'L' letter, 'N' number, ' ' whitespace, '-' skipped, anything else: another symbol."""
    if char in _SKIPPED:
        return "-"
    if char.isspace() and char not in _SEPARATORS:
        return " "
    return unicodedata.category(char)[0]


def pre_tokenize(text: str) -> list[str]:
    """Split cleaned, lower-cased text with CLIP's pre-token pattern (first alternative wins)."""
    pieces: list[str] = []
    i, n = 0, len(text)
    while i < n:
        char = text[i]
        special = next((s for s in (START_OF_TEXT, END_OF_TEXT) if text.startswith(s, i)), None)
        if special is not None:
            pieces.append(special)
            i += len(special)
            continue
        contraction = next((c for c in _CONTRACTIONS if text.startswith(c, i)), None)
        if contraction is not None:
            pieces.append(contraction)
            i += len(contraction)
            continue
        kind = _category(char)
        if kind == "L":
            j = i + 1
            while j < n and _category(text[j]) == "L":
                j += 1
        elif kind == "N":
            j = i + 1
        elif kind in (" ", "-"):
            i += 1
            continue
        else:
            j = i + 1
            while j < n and _category(text[j]) not in ("L", "N", " ", "-"):
                j += 1
        pieces.append(text[i:j])
        i = j
    return pieces


def clean_text(text: str) -> str:
    """CLIP's normalization: fix text, unescape HTML twice, collapse whitespace, lower-case."""
    try:
        import ftfy  # optional: the official cleaner
        text = ftfy.fix_text(text)
    except ImportError:
        text = unicodedata.normalize("NFC", text)
    text = html.unescape(html.unescape(text)).strip()
    return _WHITESPACE_RUN.sub(" ", text).strip().lower()


def read_merges(path: str | Path) -> list[tuple[str, str]]:
    """The merge list of a (gzip'd or plain) BPE vocabulary file; errors name the file and line."""
    path = Path(path)
    if not path.is_file():
        raise InputError("BPE vocabulary file is missing (pass the path of bpe_simple_vocab_16e6.txt.gz)",
                         file=path)
    try:
        with open(path, "rb") as raw:
            compressed = raw.read(2) == b"\x1f\x8b"
            raw.seek(0)
            data = (gzip.GzipFile(fileobj=raw) if compressed else raw).read(MAX_VOCAB_BYTES + 1)
        if len(data) > MAX_VOCAB_BYTES:
            raise InputError(f"holds more than {MAX_VOCAB_BYTES >> 20} MiB of text, far more than a BPE vocabulary "
                             "(damaged or not a vocabulary)", file=path)
        lines = data.decode("utf-8").split("\n")
    except (OSError, EOFError, UnicodeDecodeError, gzip.BadGzipFile) as exc:
        raise InputError(f"not a readable gzip'd UTF-8 BPE vocabulary ({exc})", file=path) from None
    body = lines[1:]  # the first line is a header such as "#version: 0.2"
    while body and not body[-1].strip():
        body.pop()
    merges = []
    for number, line in enumerate(body[:MAX_MERGES], start=2):
        parts = line.split()
        if len(parts) != 2:
            raise InputError(f"line {number} is not a merge of two symbols: {line!r}", file=path,
                             field="merges")
        merges.append((parts[0], parts[1]))
    if not merges:
        raise InputError("the vocabulary holds no merges", file=path, field="merges")
    return merges


class BPETokenizer:
    """``encode`` text into BPE ids and ``tokenize`` batches into fixed-length id rows."""

    def __init__(self, vocab_path: str | Path):
        self.path = Path(vocab_path)
        merges = read_merges(self.path)
        self.byte_encoder = bytes_to_unicode()
        self.byte_decoder = {c: b for b, c in self.byte_encoder.items()}
        symbols = list(self.byte_encoder.values())
        symbols += [s + END_OF_WORD for s in symbols]
        symbols += ["".join(merge) for merge in merges]
        symbols += [START_OF_TEXT, END_OF_TEXT]
        # duplicate merge results keep their last id, exactly like CLIP's dict(zip(vocab, range(n)))
        self.encoder = {symbol: index for index, symbol in enumerate(symbols)}
        self.decoder = {index: symbol for symbol, index in self.encoder.items()}
        self.vocab_size = len(symbols)
        self.bpe_ranks = {merge: rank for rank, merge in enumerate(merges)}
        self.sot_id = self.encoder[START_OF_TEXT]
        self.eot_id = self.encoder[END_OF_TEXT]
        self._cache: dict[str, list[str]] = {START_OF_TEXT: [START_OF_TEXT], END_OF_TEXT: [END_OF_TEXT]}

    def bpe(self, piece: str) -> list[str]:
        """Merge the byte symbols of one pre-token, lowest-rank pair first, until none applies."""
        cached = self._cache.get(piece)
        if cached is not None:
            return cached
        word = list(piece[:-1]) + [piece[-1] + END_OF_WORD]
        while len(word) > 1:
            pairs = {(a, b) for a, b in zip(word, word[1:])}
            best = min(pairs, key=lambda pair: self.bpe_ranks.get(pair, float("inf")))
            if best not in self.bpe_ranks:
                break
            merged, i = [], 0
            while i < len(word):
                if i + 1 < len(word) and word[i] == best[0] and word[i + 1] == best[1]:
                    merged.append(best[0] + best[1])
                    i += 2
                else:
                    merged.append(word[i])
                    i += 1
            word = merged
        self._cache[piece] = word
        return word

    def encode(self, text: str) -> list[int]:
        """Text -> BPE ids, without the start/end tokens."""
        ids: list[int] = []
        for piece in pre_tokenize(clean_text(text)):
            spelled = "".join(self.byte_encoder[b] for b in piece.encode("utf-8"))
            ids.extend(self.encoder[symbol] for symbol in self.bpe(spelled))
        return ids

    def decode(self, ids: list[int]) -> str:
        """BPE ids -> text; end-of-word markers become spaces (special tokens are spelled out)."""
        symbols = "".join(self.decoder[int(i)] for i in ids)
        raw = bytearray(self.byte_decoder[c] for c in symbols)
        return raw.decode("utf-8", errors="replace").replace(END_OF_WORD, " ")

    def tokenize(self, texts: str | list[str], context_length: int = DEFAULT_CONTEXT_LENGTH) -> torch.Tensor:
        """texts -> (n, context_length) int64 rows ``[start, ids..., end, 0, ...]``.

        Too-long texts are cut to ``context_length`` and their last id replaced by end-of-text, so
        every row ends its text with the end token (the text tower pools there).
        """
        if isinstance(texts, str):
            texts = [texts]
        if context_length < 2:
            raise InputError(f"context length must be at least 2, got {context_length}", field="context_length")
        rows = torch.zeros(len(texts), context_length, dtype=torch.long)
        for row, text in enumerate(texts):
            if not isinstance(text, str):
                raise InputError(f"text #{row} is {type(text).__name__}, not str", field="texts")
            ids = [self.sot_id] + self.encode(text) + [self.eot_id]
            if len(ids) > context_length:
                ids = ids[:context_length]
                ids[-1] = self.eot_id
            rows[row, : len(ids)] = torch.tensor(ids, dtype=torch.long)
        return rows
