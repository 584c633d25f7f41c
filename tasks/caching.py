"""Content-addressed caching for pipeline steps, layered under Prefect's task cache.

A step's *content key* is the sha256 of its kind (the task name), the ids (content hashes) of its input
artifacts, its validated config and the code version: never paths, never Python object ids.

Two layers use it:
- `cached_step` keeps an index content key -> artifact id in the home directory; a step whose
  artifact is in the store and verifies is not recomputed, even when Prefect's cache is cold
  (a killed flow, a deleted Prefect home).
- `prefect_cache_key` is the Prefect `cache_key_fn`. It mixes the id of the verified artifact into
  the key, or a fresh nonce when there is none, so that a Prefect cache hit can only ever return an
  artifact that exists and verifies; a missing or corrupt one makes the step recompute. When a step
  produces its artifact inside a Prefect task, its result is also written under the key the next
  run will compute, so that run is a plain Prefect cache hit.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tasks.code_version import code_version
from tasks.workspace import Workspace


def content_key(kind: str, inputs: dict[str, str], config: dict[str, Any], module: str) -> str:
    """`module`: the step's module; its import closure is the code version (tasks.code_version)."""
    payload = json.dumps(
        {
            "kind": kind,
            "inputs": dict(sorted(inputs.items())),
            "config": config,
            "code": code_version(module),
        },
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(payload.encode()).hexdigest()


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
        return existing
    artifact_id = produce(key)
    remember(workspace, key, artifact_id)
    _prime_prefect_cache(key, artifact_id)
    return artifact_id


def _prefect_key(content: str, artifact_id: str | None) -> str:
    return hashlib.sha256(f"{content}:{artifact_id or uuid.uuid4().hex}".encode()).hexdigest()


def _prime_prefect_cache(content: str, artifact_id: str) -> None:
    """Inside a Prefect task run: store the result under the key a later run with this artifact uses."""
    from prefect.context import TaskRunContext

    context = TaskRunContext.get()
    if context is not None and context.result_store is not None:
        context.result_store.write(obj=artifact_id, key=_prefect_key(content, artifact_id))


def prefect_cache_key(context: Any, parameters: dict[str, Any]) -> str:
    """Prefect `cache_key_fn` for tasks with the signature `(home, step, inputs, config)`.

    The content key uses the task's name, not the `step` label: two steps with the same inputs and
    config are the same computation.
    """
    workspace = Workspace(parameters["home"])
    key = content_key(
        context.task.name,
        parameters.get("inputs") or {},
        parameters.get("config") or {},
        context.task.fn.__module__,
    )
    return _prefect_key(key, lookup(workspace, key))
