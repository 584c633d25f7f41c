"""`capvector verify --all` over the store's content-cache index objects (`index/<key[:2]>/<key>.json`).

Apart from capvector.tasks.runtime.caching, whose rules it applies (`entry_problem`, `recorded_key`):
that module is in every step's code hash, and a check no step runs must not change a step's cache key.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

from capvector.artifacts.errors import ArtifactError
from capvector.artifacts.records import IntegrityVerdict
from capvector.tasks.runtime.caching import (
    COMPANION_ROLES,
    FULL_ID_RE,
    _parse_entry,
    entry_problem,
    recorded_key,
)

IndexStatus = Literal["corrupt", "missing", "mismatch"]  # an index object's verdict


def store_index_verdicts(store: Any, intact: Mapping[str, bool]) -> tuple[int, list[IntegrityVerdict]]:
    """(index objects listed, a verdict `index/<key>` per bad one) for the store's content-cache index
    (what `capvector verify --all` adds; one listing of `index/`, reads only).

    An object must be an entry (at most INDEX_ENTRY_MAX bytes, JSON naming a full id, written for its
    own key) naming an artifact of the store that is its key's result (`entry_problem`, as a hit
    checks it) whose companions are intact. `intact`: every id of the store -> whether verify found it
    whole, so no byte is hashed again here: only the named artifacts' sidecars are read."""
    keys = store.iter_index_keys()
    verdicts = []
    for key in keys:
        found = _index_object_problem(store, key, intact)
        if found is not None:
            status, detail = found
            name = key if not FULL_ID_RE.match(key) else f"index/{key}"
            verdicts.append(IntegrityVerdict(id=name, status=status, detail=detail))
    return len(keys), verdicts


def _index_object_problem(store: Any, key: str, intact: Mapping[str, bool]) -> tuple[IndexStatus, str] | None:
    """(verdict status, what is wrong) for one index object, None when a run could use it."""
    if not FULL_ID_RE.match(key):
        return "corrupt", "a stray object in the index (not index/<key[:2]>/<key>.json): no run reads it"
    miss = "; a run treats it as a miss and recomputes the step"
    try:
        data = store.index_entry(key)
    except (ValueError, OSError) as e:
        return "corrupt", f"unreadable: {e}{miss}"
    if data is None:
        return "missing", "listed, then gone when read (removed while verify ran?)"
    entry = _parse_entry(data)
    if entry is None:
        return "corrupt", f"not an index entry (a JSON object naming a full artifact id){miss}"
    if entry.get("cache_key", key) != key:
        return "mismatch", f"the entry was written for key {str(entry['cache_key'])[:16]}…{miss}"
    artifact_id = entry["artifact_id"]
    if artifact_id not in intact:
        return "missing", f"names artifact {artifact_id}, which is not in the store{miss}"
    if not intact[artifact_id]:
        return "mismatch", f"names artifact {artifact_id}, which verify found bad{miss}"
    try:
        record = store.get(artifact_id)
    except (ArtifactError, OSError) as e:
        return "corrupt", f"names artifact {artifact_id}, whose sidecar cannot be read: {e}{miss}"
    problem = entry_problem(key, entry, recorded_key(record))
    if problem is not None:
        return "mismatch", problem + miss
    lost = [
        f"{p.role} {p.id[:12]}"
        for p in record.parents
        if p.role in COMPANION_ROLES and not intact.get(p.id, False)
    ]
    if lost:
        lost_text = ", ".join(lost)
        return "mismatch", f"names {artifact_id[:12]}, registered with missing or bad {lost_text}{miss}"
    return None
