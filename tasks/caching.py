"""Content-addressed caching for pipeline steps: the one cache a step consults.

A step's *content key* is the sha256 of its kind (the task name), the ids (content hashes) of its input
artifacts, its validated config and its step code hash (tasks.step_code): never paths, never Python
object ids.

`cached_step` keeps an index content key -> artifact id in the home directory; a step whose artifact
is in the store and verifies is not recomputed (also after a killed flow or a deleted Prefect home),
and a missing or corrupt one is recomputed. The index falls back to the catalogue (artifacts record
their cache key), so finished work is never done twice.

Prefect's own task cache is not used: its hits are read back from result records in
`$PREFECT_HOME/storage`, deserialized with the serializer each record names (pickle by default), so a
planted record would run its code. Steps record whether the content cache answered them
(`step_outcomes`), and tasks.prefect_task shows those as `Cached` in Prefect.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Any

from tasks.step_code import step_code
from tasks.workspace import Workspace

# What `cached_step` did, per call, inside a `step_outcomes()` block: "cached" or "produced".
_outcomes: ContextVar[list[str] | None] = ContextVar("capvector_step_outcomes", default=None)
# Inside `probing()`, `cached_step` answers from the cache or raises NotCached; it never produces.
_probing: ContextVar[bool] = ContextVar("capvector_cache_probe", default=False)


class NotCached(LookupError):
    """Raised by `cached_step` inside `probing()` when the step would have to run."""


@contextmanager
def probing() -> Iterator[None]:
    """Run a step function only as far as its cache lookup: the flow asks whether a step is a hit
    without repeating how each step builds its key."""
    token = _probing.set(True)
    try:
        yield
    finally:
        _probing.reset(token)


@contextmanager
def step_outcomes() -> Iterator[list[str]]:
    """Collect the outcome of every `cached_step` call made inside the block (this context only)."""
    outcomes: list[str] = []
    token = _outcomes.set(outcomes)
    try:
        yield outcomes
    finally:
        _outcomes.reset(token)


def _record(outcome: str) -> None:
    outcomes = _outcomes.get()
    if outcomes is not None:
        outcomes.append(outcome)


def content_key(kind: str, inputs: dict[str, str], config: dict[str, Any], module: str) -> str:
    """`module`: the step's module; the hash of its import closure is the step code (tasks.step_code)."""
    payload = json.dumps(
        {
            "kind": kind,
            "inputs": dict(sorted(inputs.items())),
            "config": config,
            "step_code": step_code(module),
        },
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(payload.encode()).hexdigest()


def selected_by(inputs: dict[str, str]) -> list[tuple[str, str]]:
    """Parents for the selections among a step's inputs (keys `selection...`, tasks.selection): a
    value chosen on validation is an input of the step that uses it, so lineage shows why."""
    return [(aid, "selected_by") for key, aid in sorted(inputs.items()) if key.startswith("selection")]


def _index_path(workspace: Workspace, key: str) -> Path:
    return workspace.cache_dir / f"{key}.json"


def lookup(workspace: Workspace, key: str) -> str | None:
    """The artifact id stored for `key`, if it is still in the store and its content verifies.

    Without an index entry (a crash between registration and `remember`), the catalogue is asked
    for an artifact registered with this cache key, so finished work is never done twice.
    """
    path = _index_path(workspace, key)
    if path.exists():
        artifact_id = json.loads(path.read_text())["artifact_id"]
    else:
        frame = workspace.api.query(
            "SELECT id FROM artifacts WHERE json_extract_string(config, '$.cache_key') = ? "
            "ORDER BY created_at DESC LIMIT 1",
            [key],
        )
        if frame.empty:
            return None
        artifact_id = str(frame.iloc[0, 0])
    return artifact_id if workspace.artifact_is_intact(artifact_id) else None


def remember(workspace: Workspace, key: str, artifact_id: str) -> None:
    path = _index_path(workspace, key)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-")
    with os.fdopen(fd, "w") as handle:
        json.dump({"artifact_id": artifact_id}, handle)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)


def cached_step(
    workspace: Workspace,
    kind: str,
    inputs: dict[str, str],
    config: dict[str, Any],
    produce: Callable[[str], str],
) -> str:
    """Return the artifact for this step's content key, calling `produce(key)` only when needed."""
    key = content_key(kind, inputs, config, produce.__module__)
    existing = lookup(workspace, key)
    if existing is not None:
        _record("cached")
        return existing
    if _probing.get():
        raise NotCached(key)
    artifact_id = produce(key)
    remember(workspace, key, artifact_id)
    _record("produced")
    return artifact_id
