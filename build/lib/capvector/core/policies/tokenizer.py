"""Deterministic word tokenizer for instructions: no vocabulary file, no downloads.

Words are lower-cased, split on non-alphanumerics and hashed with zlib.crc32 (stable across processes
and machines, unlike Python's salted ``hash``) into ids 1..vocab_size-1; id 0 is padding.
"""

from __future__ import annotations

import re
import zlib

import torch

PAD_ID = 0
_WORD = re.compile(r"[a-z0-9]+")


def words(text: str) -> list[str]:
    """The words of an instruction, in order."""
    return _WORD.findall(text.lower())


def token_id(word: str, vocab_size: int) -> int:
    """Stable id of one word in [1, vocab_size)."""
    if vocab_size < 2:
        raise ValueError(f"vocab_size must be >= 2 (one id is padding), got {vocab_size}")
    return 1 + zlib.crc32(word.encode("utf-8")) % (vocab_size - 1)


def encode(text: str, vocab_size: int, max_length: int) -> list[int]:
    """Ids of an instruction, truncated to max_length and right-padded with PAD_ID."""
    if max_length < 1:
        raise ValueError(f"max_length must be >= 1, got {max_length}")
    ids = [token_id(w, vocab_size) for w in words(text)][:max_length]
    return ids + [PAD_ID] * (max_length - len(ids))


def encode_batch(texts: list[str], vocab_size: int, max_length: int) -> torch.Tensor:
    """(B, max_length) int64 ids for a list of instructions."""
    return torch.tensor([encode(t, vocab_size, max_length) for t in texts], dtype=torch.long)
