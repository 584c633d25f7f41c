"""One capvector home as the tasks see it: the artifact API plus local scratch and cache folders."""

from __future__ import annotations

import functools
import shutil
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from capvector.artifacts.api import ArtifactsAPI
from capvector.artifacts.errors import ArtifactError
from capvector.artifacts.home import is_local, local_cache_dir
from capvector.artifacts.provenance import installed_versions
from capvector.tasks.runtime.scratch import CheckpointMirror, scratch_url

# The libraries whose versions can change a trained weight or a score.
TRACKED_LIBRARIES = ("capvector", "torch", "mujoco", "metaworld", "numpy", "safetensors", "prefect")


class StreamedInputs:
    """Input artifacts read once and hashed as they are read, as the vector commands read theirs
    (capvector.tasks.vector_commands): `paths` to compute from with `hashes` collecting sha256s, then
    `verified()` checks every input against its id (CorruptArtifact naming it) and gives the
    `parent_hashes` of the registration, which then hashes no parent again."""

    def __init__(self, api: ArtifactsAPI, ids: dict[str, str]):
        self._store = api.store
        self._opened = {role: self._store.stream_path(i) for role, i in ids.items()}
        self.paths = {role: path for role, (path, _) in self._opened.items()}
        self.hashes: dict[Path, str] = {}

    def verified(self) -> dict[str, dict[str, str]]:
        return {rec.id: self._store.check_read(rec, path, self.hashes) for path, rec in self._opened.values()}


class Workspace:
    """Paths and the artifacts API for one home (`CAPVECTOR_HOME` or `--home`)."""

    def __init__(self, home: str):
        self.home = str(home)
        self.api = ArtifactsAPI(self.home)
        local = Path(self.home) if is_local(self.home) else local_cache_dir(self.home)
        self.local_root = local
        self.cache_dir = local / "step-cache"
        self.work_dir = local / "work"

    def artifact_is_intact(self, artifact_id: str) -> bool:
        """True when the artifact is in the store and its bytes still hash to its id."""
        try:
            self.api.path(artifact_id, verify=True)
        except (ArtifactError, OSError):
            return False
        return True

    def path(self, artifact_id: str) -> Path:
        """Local path of an artifact whose every byte was just checked against its id.

        How steps reach their inputs: bytes that changed while keeping size and mtime (bit rot,
        `cp -a`, restores) raise CorruptArtifact naming the id, before anything is computed from them
        or registered. Within one process an unchanged file is hashed once
        (capvector.artifacts.store._hash_local); each new process re-hashes. (The vector commands read each
        input once instead, hashing as they read, and check those hashes before registering:
        `ArtifactStore.stream_path`/`check_read`.)
        """
        return self.api.path(artifact_id, verify=True)

    def stream(self, ids: dict[str, str]) -> StreamedInputs:
        """Inputs by role, to be read once while hashed and checked before registering (StreamedInputs);
        `path` checks first and is read again: for inputs read by code that cannot hash as it reads."""
        return StreamedInputs(self.api, ids)

    def run_dir(self, key: str) -> Path:
        """A step's working folder, kept across a crash so training can resume from its checkpoints
        (on this machine; `checkpoint_mirror` for another)."""
        path = self.work_dir / key[:32]
        path.mkdir(parents=True, exist_ok=True)
        return path

    def checkpoint_mirror(self, key: str) -> CheckpointMirror | None:
        """Where a training run's resume checkpoints are copied so another machine can resume it
        (capvector.tasks.runtime.scratch: `CAPVECTOR_SCRATCH`, else `<home>/scratch` for a remote home); None:
        nowhere."""
        url = scratch_url(self.home)
        return CheckpointMirror(url, key) if url else None

    def finish_run_dir(self, key: str) -> None:
        """Remove a step's working folder and its checkpoints' scratch copy (its artifact is registered)."""
        shutil.rmtree(self.work_dir / key[:32], ignore_errors=True)
        mirror = self.checkpoint_mirror(key)
        if mirror is not None:
            mirror.clear()

    @contextmanager
    def scratch(self) -> Iterator[Path]:
        """A temporary folder on the same disk as the store (so the copy into it is cheap)."""
        self.work_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=self.work_dir, prefix="scratch-") as tmp:
            yield Path(tmp)


@functools.cache
def library_versions() -> dict[str, str | None]:
    return installed_versions(TRACKED_LIBRARIES)


def provenance() -> dict[str, Any]:
    """library versions and, inside a Prefect run, the flow- and task-run ids for a registration."""
    from prefect.runtime import flow_run, task_run

    return {
        "library_versions": library_versions(),
        "flow_run_id": _or_none(flow_run.id),
        "task_run_id": _or_none(task_run.id),
    }


def light_provenance() -> dict[str, Any]:
    """`provenance()`, without importing Prefect (~2 s) only to learn that this is no Prefect run (for the
    commands that register outside flows)."""
    if "prefect" not in sys.modules:
        return {"library_versions": library_versions(), "flow_run_id": None, "task_run_id": None}
    return provenance()


def _or_none(value: Any) -> str | None:
    return str(value) if value else None


@functools.cache
def workspace_for(home: str) -> Workspace:
    """The process's one Workspace per home: steps that run in the flow's process or in a pool
    worker share it, so the catalogue is opened, checked and caught up once per process. For flow
    and worker processes, which live for one run (Prefect's `serve` runs each flow run in a process
    of its own); the CLI opens a fresh one per command."""
    return Workspace(home)
