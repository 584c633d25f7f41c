"""Dataset artifacts to and from LeRobotDataset v3.0 folders, with the store's checks and lineage.

`export_dataset`: a `dataset` artifact (verified against its id) written as a v3.0 folder
(capvector.core.simulation.lerobot_export). `import_dataset`: a v3.0 folder read back
(capvector.core.simulation.lerobot_import) and registered as a `dataset` artifact whose config names
the format, the folder and the folder's content hash (the id the store would give the folder: sha256
over its files' names, sizes and sha256s), and whose parent, where the folder is a capvector export of
an artifact in this store and still holds its data, is that artifact (role `source`).

The imported artifact holds `imported.json` (format and folder hash) beside the DemoDataset files, so
that reading back an export never collapses into the exported artifact by content addressing: the
import keeps a record of its own.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from capvector.artifacts.errors import ArtifactNotFound
from capvector.artifacts.hashing import hash_file, manifest_id
from capvector.artifacts.records import ArtifactRecord
from capvector.core.simulation.demos import DemoDataset
from capvector.core.simulation.lerobot_export import write_lerobot
from capvector.core.simulation.lerobot_import import read_lerobot
from capvector.core.simulation.lerobot_layout import CODEBASE_VERSION, METAWORLD_FPS, LeRobotFormatError
from capvector.tasks.runtime.workspace import Workspace, light_provenance

FORMAT = f"LeRobotDataset {CODEBASE_VERSION}"
IMPORTED_FILE = "imported.json"


def export_dataset(workspace: Workspace, ref: str, directory: str | os.PathLike) -> dict[str, Any]:
    """Write the dataset artifact `ref` (an id or a unique prefix) as a LeRobotDataset v3.0 folder."""
    record = workspace.api.get(ref)
    if record.kind != "dataset":
        raise ValueError(f"{ref} is a {record.kind} artifact ({record.name}); --dataset takes a dataset")
    dataset = DemoDataset.load(workspace.path(record.id))  # re-hashed against its id first
    summary = write_lerobot(dataset, directory, METAWORLD_FPS, source_artifact=record.id)
    return {"dataset": record.id, "format": FORMAT, **summary}


def _snapshot(root: Path) -> dict[str, tuple[int, int]]:
    return {p.relative_to(root).as_posix(): (p.stat().st_size, p.stat().st_mtime_ns) for p in _files(root)}


def _files(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*") if p.is_file())


def folder_hash(root: Path) -> str:
    """The folder's content id, as the store names a folder artifact (`manifest_id`)."""
    files = _files(root)
    return manifest_id((p.relative_to(root).as_posix(), p.stat().st_size, hash_file(str(p))) for p in files)


def _source_parent(workspace: Workspace, source: str | None, content_hash: str) -> list[tuple[str, str]]:
    """The exported artifact as a `source` parent, when it is in this store and holds the same data."""
    if source is None:
        return []
    try:
        record = workspace.api.get(source)
    except ArtifactNotFound:
        return []
    if record.kind != "dataset":
        return []
    meta = json.loads((workspace.path(record.id) / "meta.json").read_text())
    return [(record.id, "source")] if meta.get("content_hash") == content_hash else []


def import_dataset(
    workspace: Workspace, directory: str | os.PathLike, name: str | None = None
) -> tuple[ArtifactRecord, list[str]]:
    """Register the LeRobotDataset v3.0 folder `directory` as a `dataset` artifact; its record and the
    notes on what was left out (video features, extra cameras, unknown features)."""
    root = Path(directory).resolve()
    if not root.is_dir():
        raise LeRobotFormatError(f"{directory} is not a folder")
    before = _snapshot(root)
    digest = folder_hash(root)
    read = read_lerobot(root)
    if _snapshot(root) != before:
        raise LeRobotFormatError(f"{root} changed while it was being read; run the import again")
    dataset = read.dataset
    imported = {"format": FORMAT, "folder_hash": digest}
    config = {
        "imported_from": {**imported, "path": str(root), "fps": read.fps},
        "n_steps": dataset.meta.n_steps,
        "n_episodes": dataset.meta.n_episodes,
        "content_hash": dataset.content_hash,
        "notes": read.notes,
    }
    parents = _source_parent(workspace, read.source_artifact, dataset.content_hash)
    with workspace.scratch() as tmp:
        path = dataset.save(tmp / "dataset")
        (path / IMPORTED_FILE).write_text(json.dumps(imported, indent=1, sort_keys=True) + "\n")
        record = workspace.api.register_dir(
            path, kind="dataset", name=name or f"lerobot {root.name}", config=config, parents=parents,
            **light_provenance(),
        )  # fmt: skip
    return record, read.notes
