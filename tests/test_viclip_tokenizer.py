"""CLIP BPE tokenizer on a tiny vocabulary: hand-computed merges, ids, truncation, file errors."""
from __future__ import annotations

import gzip

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from fourlegs_engine.errors import InputError
from fourlegs_engine.language.viclip.tokenizer import (MAX_MERGES, BPETokenizer, bytes_to_unicode,
                                                       clean_text, pre_tokenize)

from _viclip_helpers import TINY_MERGES, TINY_VOCAB_SIZE, write_tiny_vocab

# Ids by hand. Base symbols: printable bytes "!".."~" take ids 0..93 (id = byte - 33), then
# 161..172 take 94..105, 174..255 take 106..187, and the 68 other bytes 188..255; the same 256
# symbols with "</w>" take 256..511; merge k takes 512 + k; then <|startoftext|>, <|endoftext|>.
H, I_END, BANG_END = 104 - 33, 256 + (105 - 33), 256 + 0
HELLO, THE, CAT, BALL = 512 + 3, 512 + 5, 512 + 7, 512 + 10
SOT, EOT = 512 + len(TINY_MERGES), 512 + len(TINY_MERGES) + 1


@pytest.fixture(scope="module")
def tok(tmp_path_factory):
    return BPETokenizer(write_tiny_vocab(tmp_path_factory.mktemp("vocab") / "bpe_simple_vocab_16e6.txt.gz"))


def test_vocabulary_layout(tok):
    assert tok.vocab_size == TINY_VOCAB_SIZE == 525
    assert (tok.sot_id, tok.eot_id) == (SOT, EOT)
    assert tok.eot_id == tok.vocab_size - 1  # the text tower pools at the argmax
    table = bytes_to_unicode()
    assert len(set(table.values())) == 256
    assert table[ord("a")] == "a" and table[ord(" ")] == chr(256 + 32)  # space is the 33rd non-printable


@pytest.mark.parametrize("text, ids", [
    ("hello", [HELLO]),                      # h e -> he; l l -> ll; he ll -> hell; hell o</w> -> hello</w>
    ("HeLLo", [HELLO]),                      # lower-cased first
    ("the cat", [THE, CAT]),
    ("  the\n\tcat  ", [THE, CAT]),          # whitespace runs collapse
    ("the ball", [THE, BALL]),               # b a -> ba; l l</w> -> ll</w>; ba ll</w> -> ball</w>
    ("balls", [512 + 8, 512 + 1, 256 + 115 - 33]),  # b a -> ba; l l -> ll; then "ba ll" is no merge
    ("hi!", [H, I_END, BANG_END]),           # no merge applies; "!" is its own pre-token
    ("42", [256 + 52 - 33, 256 + 50 - 33]),  # digits are single pre-tokens: "4</w>", "2</w>"
    ("&amp;", [256 + 38 - 33]),              # HTML entity unescaped: "&</w>"
    ("é", [94 + 12 + (0xC3 - 174), 256 + 94 + (0xA9 - 161)]),  # UTF-8 bytes C3 A9 -> "Ã", "©</w>"
    ("hel", [512 + 0, 256 + (108 - 33)]),    # h e -> he; (he, l</w>) is no merge
])
def test_encode_hand_computed(tok, text, ids):
    assert tok.encode(text) == ids


def test_merge_priority_is_by_rank(tmp_path):
    # "hells" = h e l l s</w>. With "l l" ranked first: l l -> ll, then h e -> he (e ll is no merge).
    # With "e l" ranked first: e l -> el, after which neither "l l" nor "h e" can apply.
    tok_a = BPETokenizer(write_tiny_vocab(tmp_path / "a.gz", ["l l", "e l", "h e"]))
    tok_b = BPETokenizer(write_tiny_vocab(tmp_path / "b.gz", ["e l", "l l", "h e"]))
    assert [tok_a.decoder[i] for i in tok_a.encode("hells")] == ["he", "ll", "s</w>"]
    assert [tok_b.decoder[i] for i in tok_b.encode("hells")] == ["h", "el", "l", "s</w>"]


def test_tokenize_rows_and_padding(tok):
    rows = tok.tokenize(["hello", "the cat"], context_length=32)
    assert rows.shape == (2, 32) and rows.dtype == torch.int64
    assert rows[0, :3].tolist() == [SOT, HELLO, EOT] and rows[0, 3:].abs().sum() == 0
    assert rows[1, :4].tolist() == [SOT, THE, CAT, EOT]


def test_tokenize_truncates_to_32_keeping_end_token(tok):
    rows = tok.tokenize(" ".join(["hello"] * 40))
    assert rows.shape == (1, 32)
    assert rows[0].tolist() == [SOT] + [HELLO] * 30 + [EOT]
    exact = tok.tokenize(" ".join(["hello"] * 30))  # 32 ids exactly: nothing cut
    assert exact[0].tolist() == [SOT] + [HELLO] * 30 + [EOT]


def test_decode_inverts_encode(tok):
    assert tok.decode(tok.encode("the cat hello")) == "the cat hello "


@given(st.lists(st.text(alphabet="helotcabsé!?", min_size=1, max_size=8), min_size=1, max_size=6))
def test_roundtrip_property(tmp_path_factory, words):
    tok = _shared_tok(tmp_path_factory)
    text = " ".join(words)
    ids = tok.encode(text)
    assert all(0 <= i < tok.vocab_size - 2 for i in ids)
    # every pre-token decodes back, followed by one space
    assert tok.decode(ids) == "".join(p + " " for p in pre_tokenize(clean_text(text)))


_TOK = {}


def _shared_tok(factory):
    if "tok" not in _TOK:
        _TOK["tok"] = BPETokenizer(write_tiny_vocab(factory.mktemp("v") / "v.gz"))
    return _TOK["tok"]


def test_pre_tokenize_cases():
    assert pre_tokenize("it's a dog's") == ["it", "'s", "a", "dog", "'s"]
    assert pre_tokenize("x2.5%!") == ["x", "2", ".", "5", "%!"]
    assert pre_tokenize("<|startoftext|>hi<|endoftext|>") == ["<|startoftext|>", "hi", "<|endoftext|>"]
    assert pre_tokenize("''s") == ["''", "s"]
    # the official pattern's corner cases: U+0345 is matched by no class; U+001C..U+001F are not \s
    assert pre_tokenize("a\u0345b !\u0345?") == ["a", "b", "!", "?"]
    assert pre_tokenize("a\x1cb") == ["a", "\x1c", "b"]
    assert clean_text("A\x1f  B\u2003c") == "a\x1f b c"


_OFFICIAL_PATTERN = r"""<\|startoftext\|>|<\|endoftext\|>|'s|'t|'re|'ve|'m|'ll|'d|[\p{L}]+|[\p{N}]|[^\s\p{L}\p{N}]+"""


# Characters unassigned in this Python's Unicode database ("Cn") are left out: the regex package may
# follow a newer Unicode version than unicodedata.
@given(st.text(alphabet=st.characters(codec="utf-8", exclude_categories=("Cs", "Cn")), max_size=40)
       | st.text(alphabet="ab1 '!sdtlmvre<|>ñ²Ⅻ\u0301\u0345\x1c\x1f\t\n", max_size=40))
def test_pre_tokenize_matches_official_pattern(text):
    regex = pytest.importorskip("regex", reason="the regex package runs CLIP's own pattern as the oracle")
    official = regex.compile(_OFFICIAL_PATTERN, regex.IGNORECASE)
    text = clean_text(text)
    assert pre_tokenize(text) == official.findall(text)


def test_vocab_file_errors(tmp_path):
    with pytest.raises(InputError, match="missing") as err:
        BPETokenizer(tmp_path / "nope.txt.gz")
    assert "nope.txt.gz" in str(err.value)
    bad = tmp_path / "bad.txt.gz"
    bad.write_bytes(b"\x1f\x8b not really gzip")
    with pytest.raises(InputError, match="bad.txt.gz: not a readable"):
        BPETokenizer(bad)
    broken = tmp_path / "broken.txt.gz"
    broken.write_bytes(gzip.compress(b"#version: 0.2\nh e\nthree parts here\n"))
    with pytest.raises(InputError, match="line 3 is not a merge"):
        BPETokenizer(broken)
    empty = tmp_path / "empty.txt.gz"
    empty.write_bytes(gzip.compress(b"#version: 0.2\n"))
    with pytest.raises(InputError, match="no merges"):
        BPETokenizer(empty)


def test_plain_text_vocab_and_merge_cap(tmp_path):
    plain = BPETokenizer(write_tiny_vocab(tmp_path / "plain.txt", compress=False))
    assert plain.encode("hello") == [HELLO]
    # like the published file, a longer merge list is cut at 49152 - 256 - 2 merges -> 49408 ids
    symbols = list(bytes_to_unicode().values())
    merges = [f"{a} {b}" for a in symbols for b in symbols][: MAX_MERGES + 7]
    big = BPETokenizer(write_tiny_vocab(tmp_path / "big.txt.gz", merges))
    assert big.vocab_size == 49408 and big.eot_id == 49407 and big.sot_id == 49406
    assert len(big.bpe_ranks) == MAX_MERGES


def test_tokenize_rejects_non_strings(tok):
    with pytest.raises(InputError, match="text #1 is int"):
        tok.tokenize(["ok", 3])


@given(st.text(alphabet=st.characters(codec="utf-8", exclude_categories=("Cs", "Cn")), max_size=40)
       | st.text(alphabet="aB1 \t\n\x0b\x1c\x1d\x1e\x1f\u2003\u00a0&amp;;#39", max_size=40))
def test_clean_text_matches_official_cleaning(text):
    import html
    import unicodedata
    regex = pytest.importorskip("regex", reason="the regex package runs CLIP's own whitespace rule")
    try:
        import ftfy
        fixed = ftfy.fix_text(text)
    except ImportError:
        fixed = unicodedata.normalize("NFC", text)
    official = regex.sub(r"\s+", " ", html.unescape(html.unescape(fixed)).strip()).strip().lower()
    assert clean_text(text) == official
