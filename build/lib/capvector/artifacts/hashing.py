"""sha256 in one pass: hash while copying, so a stored artifact is never read again just to name it."""

import hashlib
import json
from collections.abc import Iterable
from typing import Any, BinaryIO

CHUNK = 1 << 20


def copy_and_hash(src: BinaryIO, dst: BinaryIO) -> tuple[str, int]:
    """Stream `src` into `dst` and return (sha256 hex, bytes copied)."""
    h = hashlib.sha256()
    buf = bytearray(CHUNK)
    view = memoryview(buf)
    size = 0
    while n := src.readinto(buf):
        h.update(view[:n])
        dst.write(view[:n])
        size += n
    return h.hexdigest(), size


def hash_stream(src: BinaryIO) -> tuple[str, int]:
    """sha256 hex and size of everything readable from `src`."""
    h = hashlib.sha256()
    buf = bytearray(CHUNK)
    view = memoryview(buf)
    size = 0
    while n := src.readinto(buf):
        h.update(view[:n])
        size += n
    return h.hexdigest(), size


def hash_file(path: str) -> str:
    """sha256 hex of a local file (equal to `sha256sum` output)."""
    with open(path, "rb", buffering=0) as f:
        return hash_stream(f)[0]


def canonical_json(obj: Any) -> bytes:
    """One byte string per JSON value: sorted keys, no whitespace, ASCII escapes.

    Applied to parsed JSON, so how a writer spelled a number or ordered its keys cannot change it."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True).encode()


def manifest_bytes(entries: Iterable[tuple[str, int, str]]) -> bytes:
    """Canonical manifest of a directory artifact: JSON list of [relpath, size, sha256] sorted by path.

    A directory's id is the sha256 of these bytes, so it depends on names and contents only,
    never on mtimes, permissions or the order the filesystem lists files in.
    """
    rows = sorted([p, int(s), h] for p, s, h in entries)
    return json.dumps(rows, separators=(",", ":"), ensure_ascii=False).encode()


def manifest_id(entries: Iterable[tuple[str, int, str]]) -> str:
    """Content id of a directory artifact."""
    return hashlib.sha256(manifest_bytes(entries)).hexdigest()
