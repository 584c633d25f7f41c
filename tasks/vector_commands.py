"""Vector arithmetic on any safetensors checkpoints (a file, a sharded directory or an artifact id),
with inputs and outputs registered in the catalogue so that the lineage stays complete.

A command validates and computes first, and registers only what it computed: every input is checked
and the result written into a scratch folder of the home (never the user's folder); then the outside
inputs are imported, the output is registered with them as parents, and only then is it put at `-o`.
So a command that fails (a bad input, a mismatch, NaN, a kill) registers nothing and leaves nothing
in the user's folder. An `-o` that exists already is refused, unless its bytes are exactly what the
command computed (the identical re-run after a kill between writing and registering): then that output
is registered as it is.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path

from artifacts.records import ArtifactRecord
from capvector_core import vector_ops
from capvector_core.safetensors_io import Checkpoint, CheckpointError, file_sha256
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


@dataclass(frozen=True)
class Input:
    """A command's input, located and validated but not registered yet."""

    path: Path  # where to read it: the user's path, or the store's verified copy of an artifact
    artifact_id: str | None  # None: an outside path, imported only once the command has succeeded
    kind: str


def locate(workspace: Workspace, ref: str, kind: str = "checkpoint") -> Input:
    """A path (validated as a checkpoint, not imported) or an artifact id (its verified store copy)."""
    if Path(ref).exists():
        Checkpoint(ref)  # truncated files, missing shards: refused before anything is computed
        return Input(Path(ref), None, kind)
    record = workspace.api.get(ref)
    return Input(workspace.path(record.id), record.id, kind)


def commit_input(workspace: Workspace, item: Input, digest: str | None = None) -> str:
    """The artifact id of an input, importing an outside path now. `digest`: the checkpoint digest
    (`Checkpoint.sha256`) of the bytes the command read; an import of other bytes (the file changed in
    between) is refused, so the output's parent edge always names the bytes it was computed from."""
    if item.artifact_id is not None:
        return item.artifact_id
    record = import_path(workspace, item.path, item.kind)
    if digest is not None and _checkpoint_digest(workspace, record) != digest:
        raise CheckpointError(
            f"{item.path} changed while it was being read (imported as {record.id[:12]}…, but the output "
            f"was computed from {digest[:12]}…); run the command again"
        )
    return record.id


def resolve(workspace: Workspace, ref: str, kind: str = "checkpoint") -> tuple[Path, str]:
    """(local path, artifact id) for a path or an artifact id; paths are imported."""
    item = locate(workspace, ref, kind)
    artifact_id = commit_input(workspace, item)
    return workspace.path(artifact_id), artifact_id


def _checkpoint_digest(workspace: Workspace, record: ArtifactRecord) -> str:
    """`Checkpoint.sha256` of a stored checkpoint, from the file digests its record already holds."""
    root = workspace.path(record.id)
    base = root if record.layout == "dir" else root.parent
    return Checkpoint(root).sha256({base / f.path: f.sha256 for f in record.files})


def _manifest(path: Path) -> list[tuple[str, int, str]]:
    """(relative path, size, sha256) of every file: what "the same bytes" means for a file or a folder."""
    if path.is_file():
        return [("", path.stat().st_size, file_sha256(path))]
    return sorted(
        (f.relative_to(path).as_posix(), f.stat().st_size, file_sha256(f))
        for f in path.rglob("*")
        if f.is_file()
    )


def _refuse_existing(out: Path) -> None:
    """Before any work: an `-o` that is not even a checkpoint cannot be what the command writes."""
    if not os.path.lexists(out):
        return
    try:
        Checkpoint(out)
    except (CheckpointError, OSError, ValueError):
        raise FileExistsError(f"output {out} already exists; choose another path or remove it") from None


def _refuse_unless_identical(out: Path, staged: Path) -> None:
    """An existing `-o` is accepted only when its bytes are exactly the computed output's."""
    if not os.path.lexists(out):
        return
    same = out.is_dir() == staged.is_dir() and not out.is_symlink() and _manifest(out) == _manifest(staged)
    if not same:
        raise FileExistsError(
            f"output {out} already exists and differs from what this command computes; "
            "choose another path or remove it"
        )


def _place(staged: Path, out: Path) -> None:
    """Put the registered output at `out` (if it is there already, it is identical: checked before).

    Copied under a temporary name beside `out`, then renamed (never over something that appeared in
    the meantime); on any failure the temporary copy is removed, so nothing half-written is left in
    the user's folder."""
    if os.path.lexists(out):
        return
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{uuid.uuid4().hex[:12]}"
    try:
        if staged.is_dir():
            shutil.copytree(staged, tmp)
            for f in tmp.iterdir():
                _fsync(f)
            _rename_new(tmp, out)
        else:
            shutil.copyfile(staged, tmp)
            _fsync(tmp)
            try:
                os.link(tmp, out)  # atomic, and never replaces a file (FileExistsError)
            except FileExistsError:
                raise _appeared(out) from None
            except OSError:  # a file system without hard links
                _rename_new(tmp, out)
    finally:
        with contextlib.suppress(OSError):
            shutil.rmtree(tmp) if tmp.is_dir() else tmp.unlink()


def _rename_new(tmp: Path, out: Path) -> None:
    if os.path.lexists(out):
        raise _appeared(out)
    os.rename(tmp, out)


def _appeared(out: Path) -> FileExistsError:
    return FileExistsError(f"output {out} appeared while the command ran; it was left as it is")


def _fsync(path: Path) -> None:
    with open(path, "rb") as f:
        os.fsync(f.fileno())


def _input_digests(staged: Path) -> dict[str, str]:
    """role -> sha256 of the bytes each input was read as (the output's `capvector.inputs`)."""
    inputs = json.loads(Checkpoint(staged).metadata.get("capvector.inputs", "{}"))
    return {role: entry["sha256"] for role, entry in inputs.items()}


def _register_output(
    workspace: Workspace, staged: Path, kind: str, name: str, config: dict, parents: list
) -> ArtifactRecord:
    register = workspace.api.register_dir if staged.is_dir() else workspace.api.register_file
    return register(staged, kind=kind, name=name, config=config, parents=parents, **provenance())


def extract_cli(
    workspace: Workspace,
    minuend: str,
    subtrahend: str,
    out: Path,
    base: str | None,
    include: list[str] | None,
    exclude: list[str] | None,
) -> ArtifactRecord:
    out = Path(out)
    _refuse_existing(out)
    m, s = locate(workspace, minuend), locate(workspace, subtrahend)
    b = locate(workspace, base) if base is not None else None
    with workspace.scratch() as tmp:
        staged = vector_ops.extract(
            m.path, s.path, tmp / out.name, include or None, exclude or None, base=b.path if b else None
        )
        _refuse_unless_identical(out, staged)
        digests = _input_digests(staged)
        parents = [
            (commit_input(workspace, m, digests["minuend"]), "minuend"),
            (commit_input(workspace, s, digests["subtrahend"]), "subtrahend"),
        ]
        if b is not None:
            base_digest = Checkpoint(staged).metadata.get("capvector.base_sha256")
            parents.append((commit_input(workspace, b, base_digest), "base"))
        config = {"formula": "minuend - subtrahend", "include": include, "exclude": exclude}
        record = _register_output(workspace, staged, "vector", out.stem, config, parents)
        _place(staged, out)
    return record


def finite_alphas(alphas: list[float]) -> list[float]:
    """Merge coefficients must be finite numbers: NaN or ±inf would only fail after streaming."""
    bad = [a for a in alphas if not math.isfinite(float(a))]
    if bad:
        raise ValueError(f"--alpha must be a finite number, got {', '.join(str(a) for a in bad)}")
    return [float(a) for a in alphas]


def merge_cli(
    workspace: Workspace,
    base: str,
    vectors: list[tuple[str, float]],
    out: Path,
    include: list[str] | None,
    exclude: list[str] | None,
    force: bool,
) -> ArtifactRecord:
    out = Path(out)
    alphas = finite_alphas([a for _, a in vectors])
    _refuse_existing(out)
    b = locate(workspace, base)
    located = [locate(workspace, v, "vector") for v, _ in vectors]
    with workspace.scratch() as tmp:
        staged = vector_ops.merge(
            b.path,
            [(v.path, a) for v, a in zip(located, alphas, strict=True)],
            tmp / out.name,
            include or None,
            exclude or None,
            force=force,
        )
        _refuse_unless_identical(out, staged)
        digests = _input_digests(staged)
        parents = [(commit_input(workspace, b, digests["base"]), "base")]
        for i, (v, a) in enumerate(zip(located, alphas, strict=True)):
            parents.append((commit_input(workspace, v, digests[f"vector_{i}"]), "vector", {"alpha": a}))
        config = {
            "formula": "base + sum_i alpha_i * vector_i",
            "alphas": alphas,
            "include": include,
            "exclude": exclude,
        }
        record = _register_output(workspace, staged, "checkpoint", out.stem, config, parents)
        _place(staged, out)
    return record


def stats_cli(workspace: Workspace, vector: str, base: str | None, reference: str | None) -> list[VectorStat]:
    v = locate(workspace, vector, "vector")
    b = locate(workspace, base) if base else None
    r = locate(workspace, reference, "vector") if reference else None
    rows = vector_ops.stats(v.path, base=b.path if b else None, reference_vector=r.path if r else None)
    workspace.api.register_vector_stats(
        commit_input(workspace, v),
        stat_rows(rows),
        base_id=commit_input(workspace, b) if b else None,
        reference_id=commit_input(workspace, r) if r else None,
        **provenance(),
    )
    return rows
