"""Vector arithmetic on any safetensors checkpoints (a file, a sharded directory or an artifact id),
with inputs and outputs registered in the catalogue so that the lineage stays complete.

A command validates and computes first, and registers only what it computed. Every byte is read once:
- an artifact id is read from the store's own files, hashed while it is read, and those hashes are
  checked against its id before anything is registered (`ArtifactStore.stream_path`/`check_read`);
- a path is read where it is, hashed as it is read, and the same bytes are written into a copy in the
  store's staging area while the computation runs (other files of a folder: copied by the kernel).
  Once the command succeeds the copy is registered under those hashes by a rename, so the parent edge
  names exactly the bytes the output came from; a header that changed between its check and its read
  shows in the copy and is refused;
- the output is written into the staging area too, hashed once, committed by a rename, and copied
  to `-o` (beside it under a temporary name while it is registered, renamed into place after).
So a command that fails (a bad input, a mismatch, NaN, a damaged artifact, a kill) registers nothing and
leaves nothing in the user's folder. An `-o` that exists already is refused, unless its bytes are
exactly what the command computed (the identical re-run after a kill between registering and placing
it): then that output is registered as it is.
"""

from __future__ import annotations

import contextlib
import math
import os
import shlex
import shutil
import threading
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from capvector.artifacts.hashing import hash_file, manifest_id
from capvector.artifacts.records import ArtifactRecord, utcnow
from capvector.artifacts.store import copy_file, copy_in, flush_soon, fsync_file
from capvector.core.vectors import spectrum, vector_ops
from capvector.core.vectors.safetensors_io import Checkpoint, CheckpointError, parse_size
from capvector.core.vectors.spectrum import TensorSpectrum
from capvector.core.vectors.vector_ops import VectorStat
from capvector.tasks.runtime.workspace import Workspace, light_provenance


def import_path(
    workspace: Workspace, path: str | os.PathLike, kind: str = "checkpoint", name: str | None = None
) -> ArtifactRecord:
    """Validate an outside checkpoint (headers, shards, sizes) and copy it into the store."""
    path = Path(path)
    Checkpoint(path)  # refuses truncated files and missing shards before anything is stored
    register = workspace.api.register_dir if path.is_dir() else workspace.api.register_file
    config = {"imported_from": str(path.resolve())}
    return register(path, kind=kind, name=name or path.name, config=config, **light_provenance())


@dataclass(frozen=True)
class Input:
    """A command's input, located and validated but not registered yet."""

    path: Path  # what is read: a stored artifact's own files, or the user's path (or its copy)
    kind: str
    record: ArtifactRecord | None = None  # stored: checked against it once read (`check_read`)
    source: Path | None = None  # a path: the user's, imported (its copy) once the command succeeds
    copy: Path | None = None  # its copy in the staging area
    copies: dict[Path, Path] = field(default_factory=dict)  # checkpoint file -> copy, written as read
    layout: tuple | None = None  # its tensors and metadata as validated


def locate(
    workspace: Workspace, ref: str, stage: Path, kind: str = "checkpoint", copy_now: bool = False
) -> Input:
    """An artifact id (its stored files) or a path (validated; copied into `stage` as the computation
    reads it, or at once with `copy_now`, for a computation that does not hash what it reads)."""
    if not Path(ref).exists():
        path, record = workspace.api.store.stream_path(ref)
        return Input(path, kind, record=record)
    src = Path(ref)
    ckpt = Checkpoint(src)  # bad headers, missing or escaping shards: refused before anything is read
    copy = stage / uuid.uuid4().hex / src.name
    copy.parent.mkdir()
    if copy_now:
        copy_in(src, copy)
        return Input(copy, kind, source=src, copy=copy, layout=_layout(ckpt))
    if src.is_dir():  # the shards are copied as they are read; the index and any other file now
        copies = {f: copy / f.relative_to(src) for f in ckpt.files}
        copy_in(src, copy, skip={f.relative_to(src).as_posix() for f in ckpt.files})
    else:
        copies = {src: copy}
    return Input(src, kind, source=src, copy=copy, copies=copies, layout=_layout(ckpt))


def _layout(ckpt: Checkpoint) -> tuple:
    """What a checkpoint's validated header says (tensors, where they lie, metadata)."""
    root = ckpt.path if ckpt.path.is_dir() else ckpt.path.parent
    where = {n: (s.file.relative_to(root).as_posix(), s.begin, s.end) for n, s in ckpt.specs.items()}
    return {n: (s.dtype, s.shape, *where[n]) for n, s in ckpt.specs.items()}, ckpt.metadata


def _check_copy(item: Input) -> None:
    """The copy of a path must show the tensors that were validated and read: a path changed between
    (a header rewritten, an index swapped) is refused."""
    if item.copy is not None and _layout(Checkpoint(item.copy)) != item.layout:
        raise CheckpointError(f"{item.source} changed while it was being read; run the command again")


def _locate_all(
    workspace: Workspace, refs: list[tuple[str | None, str]], stage: Path, copy_now: bool = False
) -> list[Input | None]:
    """`locate` each (ref, kind) at once (None for a ref of None; one Input for a ref named twice):
    copies made now run side by side (the kernel copies, the interpreter is free)."""
    key = {ref: os.path.realpath(ref) if Path(ref).exists() else ref for ref, _ in refs if ref is not None}
    unique = {key[ref]: (ref, kind) for ref, kind in reversed(refs) if ref is not None}

    def one(ref: str, kind: str) -> Input:
        return locate(workspace, ref, stage, kind, copy_now)

    with ThreadPoolExecutor(max(len(unique), 1)) as pool:
        found = dict(zip(unique, pool.map(one, *zip(*unique.values(), strict=True)), strict=True))
    return [None if ref is None else found[key[ref]] for ref, _ in refs]


def _check_stored(workspace: Workspace, inputs: list[Input], hashes: dict[Path, str]) -> dict:
    """Stored inputs against their ids, by the hashes taken while reading them (files not read are
    hashed now); CorruptArtifact before anything is registered. Returns `parent_hashes`."""
    store = workspace.api.store
    return {i.record.id: store.check_read(i.record, i.path, hashes) for i in inputs if i.record is not None}


@contextlib.contextmanager
def _blaming_damage(workspace: Workspace, inputs: list[Input]) -> Iterator[None]:
    """A computation that fails on a damaged stored input (NaN from a flipped bit, a torn header)
    reports the damage, not its symptom."""
    try:
        yield
    except (CheckpointError, ValueError, OSError):
        _check_stored(workspace, inputs, {})
        raise


def _commit(workspace: Workspace, items: list[Input], hashes: dict[Path, str], verified: dict) -> dict:
    """id(input) -> its artifact id; a path's copy is registered now, under the hashes of the bytes
    written into it (`vector_ops` copies what it hashes; members it did not copy are hashed by the
    store)."""
    return {id(item): _commit_one(workspace, item, hashes, verified) for item in items}


def _commit_one(workspace: Workspace, item: Input, hashes: dict[Path, str], verified: dict) -> str:
    if item.record is not None:
        return item.record.id
    if item.copy.is_dir():
        register, kw = workspace.api.register_dir, {"hashes": _relative(item.copy, hashes)}
    else:
        register, kw = workspace.api.register_file, {"sha256": hashes.get(item.copy)}
    record = register(
        item.copy,
        kind=item.kind,
        name=item.source.name,
        config={"imported_from": str(item.source.resolve())},
        **kw,
        **light_provenance(),
    )
    verified[record.id] = {f.path: f.sha256 for f in record.files}
    return record.id


def _relative(root: Path, hashes: dict[Path, str]) -> dict[str, str]:
    return {f.relative_to(root).as_posix(): h for f, h in hashes.items() if f.is_relative_to(root)}


def _output_hashes(staged: Path) -> dict[str, str]:
    """member -> sha256 of a freshly written output (a file: its own name)."""
    if staged.is_file():
        return {staged.name: hash_file(str(staged))}
    return {f.relative_to(staged).as_posix(): hash_file(str(f)) for f in staged.rglob("*") if f.is_file()}


def _manifest(path: Path) -> list[tuple[str, int, str]]:
    """(relative path, size, sha256) of every file: what "the same bytes" means for a file or a folder."""
    if path.is_file():
        return [("", path.stat().st_size, hash_file(str(path)))]
    return sorted(
        (f.relative_to(path).as_posix(), f.stat().st_size, hash_file(str(f)))
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


def _refuse_unless_identical(out: Path, staged: Path, digests: dict[str, str]) -> None:
    """An existing `-o` is accepted only when its bytes are exactly the computed output's."""
    if not os.path.lexists(out):
        return
    if staged.is_file():
        mine = [("", staged.stat().st_size, digests[staged.name])]
    else:
        mine = sorted((rel, (staged / rel).stat().st_size, h) for rel, h in digests.items())
    if out.is_dir() != staged.is_dir() or out.is_symlink() or _manifest(out) != mine:
        raise FileExistsError(
            f"output {out} already exists and differs from what this command computes; "
            "choose another path or remove it"
        )


@contextlib.contextmanager
def _placing(staged: Path, out: Path) -> Iterator[None]:
    """Put the output at `out` once the block (its registration) succeeds.

    A helper thread copies it beside `out` under a temporary name and fsyncs it while the block runs
    (its files are opened first: the block moves them into the store); then the copy is renamed into
    place, never over something that appeared meanwhile. On any failure the copy is removed, so
    nothing half-written is left in the user's folder. An `out` that is there already is identical
    (checked before) and left as it is."""
    if os.path.lexists(out):
        yield
        return
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{uuid.uuid4().hex[:12]}"
    names = (  # a folder's files, those in subfolders too (a base's processors, tokenizer, ...)
        sorted(f.relative_to(staged).as_posix() for f in staged.rglob("*") if f.is_file())
        if staged.is_dir()
        else [None]
    )
    failed: list[BaseException] = []
    with contextlib.ExitStack() as files:
        sources = [files.enter_context(open(staged / n if n else staged, "rb")) for n in names]

        def copy() -> None:
            try:
                if staged.is_dir():
                    tmp.mkdir()
                for n, f in zip(names, sources, strict=True):
                    if n:
                        (tmp / n).parent.mkdir(parents=True, exist_ok=True)
                    copy_file(f, tmp / n if n else tmp)
                    fsync_file(tmp / n if n else tmp)
            except BaseException as e:  # raised again in the command's thread
                failed.append(e)

        worker = threading.Thread(target=copy, daemon=True)
        worker.start()
        try:
            yield
        finally:
            worker.join()
    try:
        if failed:
            raise failed[0]
        if tmp.is_dir():
            _rename_new(tmp, out)
        else:
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


def _produce(
    workspace: Workspace,
    stage: Path,
    out: Path,
    inputs: list[tuple[Input, str, dict[str, Any]]],
    compute: Callable[[Path, dict[Path, str], dict[Path, Path]], Path],
    kind: str,
    config: dict[str, Any],
) -> ArtifactRecord:
    """Compute into the staging area, check the stored inputs by what was read, register the copied
    inputs and then the output (committed by a rename), and put it at `out`."""
    items = list({id(item): item for item, _, _ in inputs}.values())  # an input named twice is read once
    copies = {f: c for item in items for f, c in item.copies.items()}
    hashes: dict[Path, str] = {}
    (stage / "output").mkdir()
    with _blaming_damage(workspace, items):
        staged = compute(stage / "output" / out.name, hashes, copies)
    for copy in copies.values():  # the fsync before their commit: started now, run while the output is hashed
        flush_soon(copy)
    verified = _check_stored(workspace, items, hashes)
    for item in items:
        _check_copy(item)
    with _placing(staged, out):
        digests = _output_hashes(staged)
        _refuse_unless_identical(out, staged, digests)
        ids = _commit(workspace, items, hashes, verified)
        parents = [(ids[id(item)], role, attrs) for item, role, attrs in inputs]
        if staged.is_dir():
            register, kw = workspace.api.register_dir, {"hashes": digests}
        else:
            register, kw = workspace.api.register_file, {"sha256": digests[staged.name]}
        return register(
            staged, kind=kind, name=out.stem, config=config, parents=parents, parent_hashes=verified,
            **kw, **light_provenance(),
        )  # fmt: skip


@dataclass(frozen=True)
class RealCheckpoints:
    """The options that fit real checkpoints to each other and shape the output (`--dtype`, ...)."""

    dtype: str | None = None
    out_dtype: str | None = None
    strip_prefix: str | None = None
    add_prefix: str | None = None
    out_shard_size: str | None = None  # e.g. 5GB; None: 2 GiB shards, as before

    def kwargs(self) -> dict[str, Any]:
        found = {k: getattr(self, k) for k in ("dtype", "out_dtype", "strip_prefix", "add_prefix")}
        if self.out_shard_size is not None:
            found["max_shard_bytes"] = parse_size(self.out_shard_size)
        return found

    def flags(self) -> list[str]:
        """The options as given, in the command's spelling (for the card)."""
        return [
            f"--{k.replace('_', '-')} {shlex.quote(str(v))}" for k, v in vars(self).items() if v is not None
        ]

    def config(self) -> dict[str, Any]:
        return {k: v for k, v in vars(self).items() if v is not None}


def _input_ids(roles: dict[str, Input | None], hashes: dict[Path, str]) -> Callable[[str], str | None]:
    """role -> the artifact id its input has (stored) or will have once registered (a path: the id of
    its copy, from the hashes taken while it was read)."""

    def find(role: str) -> str | None:
        item = roles.get(role)
        if item is None:
            return None
        if item.record is not None:
            return item.record.id
        if item.copy.is_file():
            return hashes.get(item.copy)
        entries = [
            (f.relative_to(item.copy).as_posix(), f.stat().st_size, hashes.get(f) or hash_file(str(f)))
            for f in item.copy.rglob("*")
            if f.is_file()
        ]
        return manifest_id(entries)

    return find


def _carry_from(item: Input) -> Path:
    """Where a reference input's other files are read: its copy (what is registered) or its stored folder."""
    return item.copy if item.copy is not None else item.path


def _filters(include: list[str] | None, exclude: list[str] | None) -> list[str]:
    return [f"--include {shlex.quote(p)}" for p in include or []] + [
        f"--exclude {shlex.quote(p)}" for p in exclude or []
    ]


def extract_cli(
    workspace: Workspace,
    minuend: str,
    subtrahend: str,
    out: Path,
    base: str | None,
    include: list[str] | None,
    exclude: list[str] | None,
    real: RealCheckpoints | None = None,
) -> ArtifactRecord:
    out = Path(out)
    real = real or RealCheckpoints()
    options = real.kwargs()
    _refuse_existing(out)
    with workspace.api.store.staging() as stage:
        refs = [(minuend, "checkpoint"), (subtrahend, "checkpoint"), (base, "checkpoint")]
        m, s, b = _locate_all(workspace, refs, stage)
        inputs = [(m, "minuend", {}), (s, "subtrahend", {})] + ([(b, "base", {})] if b else [])
        command = " ".join(
            ["capvector vector extract {minuend} {subtrahend}"]
            + (["--base {base}"] if b else [])
            + _filters(include, exclude)
            + real.flags()
            + ["-o OUTPUT"]
        )
        settings = {"include": include, "exclude": exclude, **real.config()}
        card = vector_ops.Card(command=command, settings=settings)

        def compute(dst: Path, hashes: dict[Path, str], copies: dict[Path, Path]) -> Path:
            flt, base_path = (include or None, exclude or None), b.path if b else None
            return vector_ops.extract(
                m.path, s.path, dst, *flt, base=base_path, hashes=hashes, copies=copies, **options,
                carry_from=_carry_from(m), card=card,
                input_ids=_input_ids({"minuend": m, "subtrahend": s, "base": b}, hashes),
            )  # fmt: skip

        config = {"formula": "minuend - subtrahend", "include": include, "exclude": exclude, **real.config()}
        return _produce(workspace, stage, out, inputs, compute, "vector", config)


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
    real: RealCheckpoints | None = None,
) -> ArtifactRecord:
    out = Path(out)
    real = real or RealCheckpoints()
    options = real.kwargs()
    alphas = finite_alphas([a for _, a in vectors])
    _refuse_existing(out)
    with workspace.api.store.staging() as stage:
        refs = [(base, "checkpoint")] + [(v, "vector") for v, _ in vectors]
        b, *located = _locate_all(workspace, refs, stage)
        pairs = list(zip(located, alphas, strict=True))
        inputs = [(b, "base", {})] + [(v, "vector", {"alpha": a}) for v, a in pairs]
        command = " ".join(
            ["capvector vector merge {base}"]
            + [f"--vector {{vector_{i}}} --alpha {a!r}" for i, a in enumerate(alphas)]
            + _filters(include, exclude)
            + real.flags()
            + (["--force"] if force else [])
            + ["-o OUTPUT"]
        )
        settings = {"include": include, "exclude": exclude, **real.config(), "force": force or None}
        card = vector_ops.Card(command=command, settings=settings)
        roles = {"base": b, **{f"vector_{i}": v for i, v in enumerate(located)}}

        def compute(dst: Path, hashes: dict[Path, str], copies: dict[Path, Path]) -> Path:
            vecs, flt = [(v.path, a) for v, a in pairs], (include or None, exclude or None)
            return vector_ops.merge(
                b.path, vecs, dst, *flt, force=force, hashes=hashes, copies=copies, **options,
                carry_from=_carry_from(b), card=card, input_ids=_input_ids(roles, hashes),
            )  # fmt: skip

        config = {
            "formula": "base + sum_i alpha_i * vector_i",
            "alphas": alphas,
            "include": include,
            "exclude": exclude,
            **real.config(),
        }
        return _produce(workspace, stage, out, inputs, compute, "checkpoint", config)


def mean_cli(
    workspace: Workspace, vectors: list[str], out: Path, method: str = "mean", density: float = 0.2
) -> ArtifactRecord:
    """γ̄ = the mean (or TIES merge) of K ≥ 2 vectors, each a path or an artifact id; an edge per input
    (role `vector`, its position as `index`)."""
    out = Path(out)
    vector_ops.check_mean_args(len(vectors), method, density)
    _refuse_existing(out)
    with workspace.api.store.staging() as stage:
        located = _locate_all(workspace, [(v, "vector") for v in vectors], stage)
        _refuse_repeated(vectors, located)
        inputs = [(v, "vector", {"index": i}) for i, v in enumerate(located)]

        def compute(dst: Path, hashes: dict[Path, str], copies: dict[Path, Path]) -> Path:
            paths = [v.path for v in located]
            return vector_ops.mean(paths, dst, method, density, hashes=hashes, copies=copies)

        config = {"formula": vector_ops.MEAN_FORMULAS[method], "method": method, "vectors": len(vectors)}
        if method == "ties":
            config["density"] = density
        return _produce(workspace, stage, out, inputs, compute, "vector", config)


def _refuse_repeated(refs: list[str], located: list[Input]) -> None:
    """The same vector named twice (two spellings of a path, an id and its prefix) would count twice."""
    first: dict[str, int] = {}
    for i, (ref, item) in enumerate(zip(refs, located, strict=True)):
        key = item.record.id if item.record is not None else os.path.realpath(item.source)
        j = first.setdefault(key, i)
        if j != i:
            same = "is named twice" if refs[j] == ref else f"and {refs[j]!r} are the same vector"
            raise ValueError(f"{ref!r} {same} (inputs {j} and {i}): each vector counts once in a mean")


def _measure(
    workspace: Workspace,
    refs: list[tuple[str | None, str]],
    measure: Callable[..., Any],
    register: Callable[[Any, list[str | None], dict], ArtifactRecord],
) -> tuple[Any, ArtifactRecord]:
    """A measurement of its inputs (`measure(*paths)`, None for a ref of None) and its artifact.

    The inputs are copied now (a measurement does not hash what it reads); once it succeeds, the stored
    ones are checked against their ids (hashed now) and the copies against what was read, the copies
    are registered, and `register(result, input ids, parent_hashes)` stores the result."""
    with workspace.api.store.staging() as stage:
        located = _locate_all(workspace, refs, stage, copy_now=True)
        items = list({id(x): x for x in located if x is not None}.values())
        with _blaming_damage(workspace, items):
            result = measure(*(x.path if x is not None else None for x in located))
        verified = _check_stored(workspace, items, {})
        for item in items:
            _check_copy(item)
        ids = _commit(workspace, items, {}, verified)
        record = register(result, [ids[id(x)] if x is not None else None for x in located], verified)
    return result, record


def stats_cli(
    workspace: Workspace, vector: str, base: str | None, reference: str | None
) -> tuple[list[VectorStat], ArtifactRecord, bool]:
    """The vector's statistics, their `vector_stats` artifact, and whether it was recorded before: the
    same vector, base and reference give the same document, hence the same artifact (content
    addressing), so a repeated call reuses it and registers nothing new."""
    from capvector.tasks.steps.vectors import stat_rows  # imports Prefect: only this command needs it

    def register(rows: list[VectorStat], ids: list[str | None], verified: dict) -> ArtifactRecord:
        vector_id, base_id, reference_id = ids
        return workspace.api.register_vector_stats(
            vector_id, stat_rows(rows), base_id=base_id, reference_id=reference_id, parent_hashes=verified,
            **light_provenance(),
        )  # fmt: skip

    started = utcnow()
    refs = [(vector, "vector"), (base or None, "checkpoint"), (reference or None, "vector")]
    rows, record = _measure(workspace, refs, vector_ops.stats, register)
    return rows, record, record.created_at < started


def spectrum_cli(
    workspace: Workspace, a: str, b: str | None = None
) -> tuple[list[TensorSpectrum], ArtifactRecord, bool]:
    """The spectrum of B − A (two checkpoints), or of the vector A alone without B; its `vector_spectrum`
    artifact; and whether it was recorded before (the same inputs give the same document, hence the same
    artifact, as for `stats_cli`)."""

    def register(rows: list[TensorSpectrum], ids: list[str | None], verified: dict) -> ArtifactRecord:
        vector_id, subtrahend_id = ids
        return workspace.api.register_vector_spectrum(
            vector_id, [r.model_dump() for r in rows], subtrahend_id=subtrahend_id, parent_hashes=verified,
            **light_provenance(),
        )  # fmt: skip

    started = utcnow()
    if b is None:
        refs = [(a, "vector"), (None, "checkpoint")]
    else:
        refs = [(b, "checkpoint"), (a, "checkpoint")]
    rows, record = _measure(workspace, refs, spectrum.spectrum, register)
    return rows, record, record.created_at < started
