"""Durable writes, the one helper every package uses: a file or folder is either whole at its final
name or absent, and survives a power cut once the call returns.

POSIX persists a rename only once the directory holding the new entry is fsynced, and a renamed file's
bytes only once the file itself is; each writer used to repeat those steps. Standard library only, so
that the store (no torch) and the library (no store) can both import it.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path


def fsync_dir(path: str | os.PathLike[str]) -> None:
    """Make the entries of a directory (a rename into it, a new file) durable."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_files(folder: str | os.PathLike[str]) -> None:
    """fsync every file directly in `folder`, then the folder: what a rename of it will expose."""
    for child in Path(folder).iterdir():
        if child.is_file():
            with open(child, "rb") as handle:
                os.fsync(handle.fileno())
    fsync_dir(folder)


def write_atomic(path: str | os.PathLike[str], data: bytes | str) -> None:
    """Replace `path` with `data`: written under a temporary name beside it, fsynced, renamed over it,
    and the rename made durable. A reader sees the old bytes or the new ones, never a mix."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:12]}")
    try:
        with open(tmp, "wb") as out:
            out.write(data.encode() if isinstance(data, str) else data)
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)
