"""Content-addressed caching for pipeline steps: the one cache a step consults.

A step's *content key* is the sha256 of its kind (the task name), the ids (content hashes) of its input
artifacts, its validated config and its step code hash (capvector.tasks.runtime.step_code): never paths, never
Python object ids. A step that gives its config as a model (training, demo collection, evaluation) is keyed on
`capvector.core.training.execution.result_config`: the config without the fields that only say where or how
fast it runs (train.device, num_threads, checkpoint_every, keep_checkpoints; the demos' workers; evaluation's
batch_size; that module says why each cannot change the result). So a run asked for on `cuda:0` is a hit for
the same run trained on a CPU; the record says where it ran.

`cached_step` keeps an index content key -> artifact id in the home directory; a step whose artifact
is in the store and verifies is not recomputed (also after a killed flow or a deleted Prefect home),
and a missing or corrupt one is recomputed. The index falls back to the catalogue (artifacts record
their cache key), so finished work is never done twice.

A remote home's folder index lives on each machine (its local cache), so the entry is also written to
the store as one object per key (`index/<key[:2]>/<key>.json`, ArtifactStore.put_index_entry), after
the artifact it names is committed. A machine without a local entry asks that object (one GET) before
the catalogue: a brand-new machine answers a cached plan without listing the store to catch its
catalogue up. The object is checked as a local entry is (below); one that cannot be read as an entry
(cut short, not JSON, not a full id) is a miss with one warning line, and the recomputation rewrites it.

The index is not trusted blindly. A hit must be the artifact this key produced: its record's
`config.cache_key` is the lookup's key (the key hashes kind, inputs, config and code, so this also
checks the recorded step config), or the entry was written for this key when its computation
returned an artifact first recorded under another key (the same bytes, e.g. after a code change:
content addressing keeps the first record) and still says so. Artifacts the step registered beside
its result and that the result names as parents (roles in COMPANION_ROLES: training snapshots, a
LoRA adapter) must be intact too. Anything else is a miss: recomputed, never used, with one warning
line naming the step (`capvector verify --all` lists such entries: `index_problems`).

Two runs on one home: a step is computed and registered under an exclusive lock per content key
(`<home>/locks/<key>.lock`, flock: the kernel drops it when its holder dies, even by kill -9). A run
that finds the lock held waits, then looks the cache up again, so it reuses the other's artifact.

Prefect's own task cache is not used: its hits are read back from result records in
`$PREFECT_HOME/storage`, deserialized with the serializer each record names (pickle by default), so a
planted record would run its code. Steps record whether the content cache answered them
(`step_outcomes`), and capvector.tasks.runtime.prefect_task shows those as `Cached` in Prefect.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import re
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from capvector.artifacts.errors import ArtifactError
from capvector.artifacts.home import is_local, local_cache_dir
from capvector.core.training.execution import result_config
from capvector.durable import write_atomic
from capvector.tasks.runtime.step_code import step_code
from capvector.tasks.runtime.workspace import Workspace

# Parent roles that name artifacts the step registered itself, beside its result: a hit needs them too.
COMPANION_ROLES = ("snapshot", "adapter")
FULL_ID_RE = re.compile(r"^[0-9a-f]{64}$")

# What `cached_step` did, per call, inside a `step_outcomes()` block: "cached" or "produced".
_outcomes: ContextVar[list[str] | None] = ContextVar("capvector_step_outcomes", default=None)
# Inside `probing()`, `cached_step` answers from the cache or raises NotCached; it never produces.
_probing: ContextVar[bool] = ContextVar("capvector_cache_probe", default=False)
# The label of the pipeline step being run (capvector.tasks.runtime.prefect_task), for the lines `cached_step`
# writes.
_step_label: ContextVar[str | None] = ContextVar("capvector_step_label", default=None)


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
def step_label(step: str) -> Iterator[None]:
    """Name the step whose `cached_step` calls run inside the block (its warnings name it)."""
    token = _step_label.set(step)
    try:
        yield
    finally:
        _step_label.reset(token)


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


def content_key(kind: str, inputs: dict[str, str], config: dict[str, Any] | BaseModel, module: str) -> str:
    """`module`: the step's module; the hash of its import closure is the step code
    (capvector.tasks.runtime.step_code).

    `config`: a validated model, keyed without its ExecutionOnly fields (see the module's docstring), or
    a plain dict, hashed as it is."""
    payload = json.dumps(
        {
            "kind": kind,
            "inputs": dict(sorted(inputs.items())),
            "config": result_config(config) if isinstance(config, BaseModel) else config,
            "step_code": step_code(module),
        },
        sort_keys=True,
        default=str,
    )
    return hashlib.sha256(payload.encode()).hexdigest()


def selected_by(inputs: dict[str, str]) -> list[tuple[str, str]]:
    """Parents for the selections among a step's inputs (keys `selection...`,
    capvector.tasks.steps.selection): a
    value chosen on validation is an input of the step that uses it, so lineage shows why."""
    return [(aid, "selected_by") for key, aid in sorted(inputs.items()) if key.startswith("selection")]


def index_dir(home: str) -> Path:
    """The step-cache index of a home (Workspace.cache_dir), without opening the home's API."""
    local = Path(home) if is_local(home) else local_cache_dir(home)
    return local / "step-cache"


def _index_path(workspace: Workspace, key: str) -> Path:
    return workspace.cache_dir / f"{key}.json"


def _read_entry(path: Path) -> dict[str, Any] | None:
    """An index entry, or None when absent or unreadable (a cut-short file is no answer)."""
    try:
        entry = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return entry if isinstance(entry, dict) and isinstance(entry.get("artifact_id"), str) else None


def recorded_key(record: Any) -> str | None:
    """The cache key an artifact was registered under (its record's `config.cache_key`)."""
    key = (record.config or {}).get("cache_key")
    return key if isinstance(key, str) else None


def entry_problem(key: str, entry: dict[str, Any] | None, recorded: str | None) -> str | None:
    """Why the artifact an entry (None: the catalogue's answer) names cannot be this key's result.

    `recorded`: the key in the artifact's record. It must be `key`, unless the entry was written for
    `key` over an artifact first recorded under another key (same bytes) and says which."""
    if recorded == key:
        return None
    if entry is not None and entry.get("cache_key") == key and entry.get("recorded_under", key) == recorded:
        return None
    where = f"key {recorded[:16]}…" if recorded else "no cache key"
    return f"the cache names {entry['artifact_id'][:12] if entry else 'an artifact'}, recorded under {where}"


def _parse_entry(data: bytes) -> dict[str, Any] | None:
    """An index object's entry: a JSON object naming a full artifact id (64 hex), else None."""
    try:
        entry = json.loads(data)
    except ValueError:
        return None
    ok = isinstance(entry, dict) and isinstance(entry.get("artifact_id"), str)
    return entry if ok and FULL_ID_RE.match(entry["artifact_id"]) else None


def _store_entry(workspace: Workspace, key: str) -> tuple[dict[str, Any] | None, str | None]:
    """A remote home's index object of `key` (one GET): (entry, None), (None, None) when there is
    none or it could not be fetched (the catalogue is asked instead), or (None, why) when it cannot
    be read as an entry."""
    store = workspace.api.store
    try:
        data = store.index_entry(key)
    except OSError:  # the store did not answer: no reason to distrust the object, nor to use it
        return None, None
    except ValueError as e:
        return None, f"index object of key {key[:16]}… unreadable: {e}"
    if data is None:
        return None, None
    entry = _parse_entry(data)
    if entry is None:
        return None, f"index object {store.index_entry_path(key)} is not an index entry"
    return entry, None


def _find(workspace: Workspace, key: str) -> tuple[str | None, str | None]:
    """(artifact id of a valid hit or None, why an answer the index gave was refused or None)."""
    entry = _read_entry(_index_path(workspace, key))
    if entry is None and not workspace.api.store.local:
        entry, problem = _store_entry(workspace, key)
        if problem is not None:
            return None, problem
    if entry is not None:
        artifact_id = entry["artifact_id"]
    else:
        artifact_id = workspace.api.cached_result(key)
        if artifact_id is None:
            return None, None
    try:
        record = workspace.api.get(artifact_id)
    except (ArtifactError, OSError):  # gone (or its sidecar is): a plain miss
        return None, None
    problem = entry_problem(key, entry, recorded_key(record))
    if problem is not None:
        return None, problem
    if not workspace.artifact_is_intact(artifact_id):
        return None, None
    lost = [
        f"{p.role} {p.id[:12]}"
        for p in record.parents
        if p.role in COMPANION_ROLES and not workspace.artifact_is_intact(p.id)
    ]
    if lost:
        return None, f"{artifact_id[:12]} names missing or corrupt artifacts it was registered with: " + (
            ", ".join(lost)
        )
    return artifact_id, None


def lookup(workspace: Workspace, key: str) -> str | None:
    """The artifact id stored for `key`, if it is still in the store, verifies, is this key's result
    (see the module's docstring) and every artifact registered with it is intact.

    Without an index entry (a crash between registration and `remember`), the catalogue is asked
    for an artifact registered with this cache key, so finished work is never done twice.
    """
    return _find(workspace, key)[0]


def remember(workspace: Workspace, key: str, artifact_id: str) -> None:
    """Write the index entry key -> artifact id, with the key and the key the artifact is recorded
    under (they differ only when this computation gave bytes first registered by another key)."""
    try:
        recorded = recorded_key(workspace.api.get(artifact_id))
    except (ArtifactError, OSError):
        recorded = None
    data = json.dumps({"artifact_id": artifact_id, "cache_key": key, "recorded_under": recorded})
    write_atomic(_index_path(workspace, key), data)
    if not workspace.api.store.local:  # the machine's folder is not shared: the store's object is
        try:
            workspace.api.store.put_index_entry(key, data.encode())
        except OSError as e:  # the artifact stands; other machines find it by the catalogue instead
            warn(f"index object of key {key[:16]}… not written to the store ({e})")


def index_problems(home: str, api: Any) -> list[tuple[str, str]]:
    """(key, problem) for each index entry that names an artifact recorded under another key (what
    `capvector verify --all` reports; a run treats such an entry as a miss). Reads only."""
    problems = []
    folder = index_dir(home)
    for path in sorted(folder.glob("*.json")) if folder.is_dir() else []:
        key = path.stem
        entry = _read_entry(path)
        if entry is None:
            problems.append((key, "unreadable entry"))
            continue
        try:
            record = api.store.get(entry["artifact_id"])
        except (ArtifactError, OSError):
            continue  # a missing artifact is recomputed by the next run; verify reports the store's own
        if entry.get("cache_key", key) != key:
            problems.append((key, f"the entry was written for key {str(entry['cache_key'])[:16]}…"))
            continue
        problem = entry_problem(key, entry, recorded_key(record))
        if problem is not None:
            problems.append((key, problem))
    return problems


def warn(line: str) -> None:
    """One warning line on stderr (also when progress is quiet) and in the run's log file."""
    from capvector.tasks.runtime.progress import emit

    emit(f"warning: {line}", always=True)


@contextmanager
def step_lock(workspace: Workspace, key: str, label: str) -> Iterator[None]:
    """Hold the exclusive lock of content key `key` (an flock, released by the kernel when its holder
    dies); says once that it waits when another process holds it."""
    path = workspace.local_root / "locks" / f"{key}.lock"
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            from capvector.tasks.runtime.progress import emit

            emit(f"[{label}] waiting for another run that is computing this step ({path.name})")
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing the only descriptor releases the lock


def cached_step(
    workspace: Workspace,
    kind: str,
    inputs: dict[str, str],
    config: dict[str, Any] | BaseModel,
    produce: Callable[[str], str],
    step: str | None = None,
    module: str | None = None,
) -> str:
    """Return the artifact for this step's content key, calling `produce(key)` only when needed.

    `step`: the step's label for warnings (default: the pipeline step being run, else `kind`).
    `module`: the step's module, whose code the key hashes (default: `produce`'s). A refused index
    answer is warned about once, and recomputed. Compute-and-register runs under the key's lock; the
    cache is asked again once it is held (another run may just have finished it).
    """
    key = content_key(kind, inputs, config, module or produce.__module__)
    existing, problem = _find(workspace, key)
    if existing is not None:
        _record("cached")
        return existing
    if _probing.get():
        raise NotCached(key)
    label = step or _step_label.get() or kind
    if problem is not None:
        warn(f"step {label!r}: cache entry refused, recomputing: {problem}")
    with step_lock(workspace, key, label):
        existing, _ = _find(workspace, key)
        if existing is not None:
            _record("cached")
            return existing
        artifact_id = produce(key)
        remember(workspace, key, artifact_id)
    _record("produced")
    return artifact_id
