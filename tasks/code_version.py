"""The code version that goes into every cache key and artifact record.

Prefect's default cache policy hashes only the task's own source; a change in a helper it calls
(a loss, a data loader) would silently reuse stale results. We hash every Python source file of
the packages whose behaviour decides an artifact's content.
"""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path

import capvector_core
import tasks

_PACKAGES = (capvector_core, tasks)


@functools.cache
def code_version() -> str:
    """sha256 (hex, 16 chars) over the relative paths and bytes of all package sources."""
    digest = hashlib.sha256()
    for package in _PACKAGES:
        root = Path(package.__file__).parent
        for path in sorted(root.rglob("*.py")):
            digest.update(f"{package.__name__}/{path.relative_to(root).as_posix()}\0".encode())
            digest.update(path.read_bytes())
            digest.update(b"\0")
    return digest.hexdigest()[:16]
