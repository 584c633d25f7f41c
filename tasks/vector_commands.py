"""Vector arithmetic on any safetensors checkpoints (a file, a sharded directory or an artifact id),
with inputs and outputs registered in the catalogue so that the lineage stays complete.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from artifacts.records import ArtifactRecord
from capvector_core import vector_ops
from capvector_core.safetensors_io import Checkpoint, CheckpointError
from capvector_core.vector_ops import VectorStat
from tasks.vectors import stat_rows
from tasks.workspace import Workspace, provenance


def import_path(
    workspace: Workspace, path: str | os.PathLike, kind: str = "checkpoint", name: str | None = None
) -> ArtifactRecord:
    """Validate an outside checkpoint (headers, shards, sizes) and copy it into the store."""
    path = Path(path)
    Checkpoint(path)  # refuses truncated files and missing shards before anything is stored
    register = workspace.api.register_dir if path.is_dir() else workspace.api.register_file
    return register(
        path, kind=kind, name=name or path.name, config={"imported_from": str(path.resolve())}, **provenance()
    )


def resolve(workspace: Workspace, ref: str, kind: str = "checkpoint") -> tuple[Path, str]:
    """(local path, artifact id) for a path or an artifact id; paths are imported first."""
    if Path(ref).exists():
        record = import_path(workspace, ref, kind)
        return workspace.path(record.id), record.id
    record = workspace.api.get(ref)
    return workspace.path(record.id), record.id


def _register_output(
    workspace: Workspace, out: Path, kind: str, name: str, config: dict, parents: list
) -> ArtifactRecord:
    register = workspace.api.register_dir if out.is_dir() else workspace.api.register_file
    return register(out, kind=kind, name=name, config=config, parents=parents, **provenance())


def _refuse_existing(out: Path) -> None:
    if out.exists():
        raise FileExistsError(f"output {out} already exists; choose another path or remove it")


def extract_cli(
    workspace: Workspace,
    minuend: str,
    subtrahend: str,
    out: Path,
    base: str | None,
    include: list[str] | None,
    exclude: list[str] | None,
) -> ArtifactRecord:
    _refuse_existing(out)
    m_path, m_id = resolve(workspace, minuend)
    s_path, s_id = resolve(workspace, subtrahend)
    parents = [(m_id, "minuend"), (s_id, "subtrahend")]
    b_path = None
    if base is not None:
        b_path, b_id = resolve(workspace, base)
        parents.append((b_id, "base"))
    vector_ops.extract(m_path, s_path, out, include or None, exclude or None, base=b_path)
    return _register_output(
        workspace,
        out,
        "vector",
        out.stem,
        {"formula": "minuend - subtrahend", "include": include, "exclude": exclude},
        parents,
    )


def merge_cli(
    workspace: Workspace,
    base: str,
    vectors: list[tuple[str, float]],
    out: Path,
    include: list[str] | None,
    exclude: list[str] | None,
    force: bool,
) -> ArtifactRecord:
    _refuse_existing(out)
    b_path, b_id = resolve(workspace, base)
    resolved = [(resolve(workspace, v, "vector"), alpha) for v, alpha in vectors]
    try:
        vector_ops.merge(
            b_path, [(p, a) for (p, _), a in resolved], out, include or None, exclude or None, force=force
        )
    except CheckpointError:
        if out.exists():
            shutil.rmtree(out) if out.is_dir() else out.unlink()
        raise
    parents = [(b_id, "base")] + [(vid, "vector", {"alpha": a}) for (_, vid), a in resolved]
    alphas = [a for _, a in resolved]
    return _register_output(
        workspace,
        out,
        "checkpoint",
        out.stem,
        {
            "formula": "base + sum_i alpha_i * vector_i",
            "alphas": alphas,
            "include": include,
            "exclude": exclude,
        },
        parents,
    )


def stats_cli(workspace: Workspace, vector: str, base: str | None, reference: str | None) -> list[VectorStat]:
    v_path, v_id = resolve(workspace, vector, "vector")
    b_path, b_id = resolve(workspace, base) if base else (None, None)
    r_path, r_id = resolve(workspace, reference, "vector") if reference else (None, None)
    rows = vector_ops.stats(v_path, base=b_path, reference_vector=r_path)
    workspace.api.register_vector_stats(
        v_id, stat_rows(rows), base_id=b_id, reference_id=r_id, **provenance()
    )
    return rows
