"""Pydantic records: the sidecar of every artifact and the JSON documents the catalogue indexes."""

import hashlib
import json
import posixpath
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from capvector.artifacts.errors import PathEscape
from capvector.artifacts.hashing import canonical_json

# 2: the sidecar carries `metadata_sha256`, a seal over its metadata. 1: written before sealing
# ("unsealed"): still read, reported by `capvector verify`.
SIDECAR_FORMAT = 2
SEAL_FIELD = "metadata_sha256"
ID_RE = re.compile(r"^[0-9a-f]{64}$")


def utcnow() -> datetime:
    """Naive UTC now: the catalogue stores UTC TIMESTAMPs, so no timezone conversion can creep in."""
    return datetime.now(UTC).replace(tzinfo=None)


def safe_relpath(path: str) -> str:
    """Normalise a member path of an artifact and refuse anything that could leave its directory."""
    if not path or "\\" in path or "\x00" in path:
        raise PathEscape(f"invalid member path {path!r}")
    norm = posixpath.normpath(path)
    if norm.startswith("/") or norm == ".." or norm.startswith("../") or norm == ".":
        raise PathEscape(f"path {path!r} escapes the artifact directory")
    return norm


class ParentRef(BaseModel):
    """One lineage edge into an artifact; `attrs` carries edge facts such as a merge's alpha."""

    model_config = ConfigDict(frozen=True)
    id: str
    role: str
    attrs: dict[str, Any] = Field(default_factory=dict)


ParentLike = ParentRef | tuple[str, str] | tuple[str, str, dict[str, Any]]
# artifact id -> {member path: sha256} the caller took while reading that artifact's files
ParentHashes = Mapping[str, Mapping[str, str]]
# What a registration may say about its run besides kind, name, config and parents.
PROVENANCE_KEYWORDS = ("library_versions", "flow_run_id", "task_run_id", "parent_hashes")


@dataclass(frozen=True)
class ArtifactMeta:
    """Everything a registration says about an artifact besides its bytes: what its sidecar records
    (kind, name, config, parents, library versions, run ids) and `parent_hashes` (see
    ArtifactStore._check_parent). One value, so the store's write path hands it on whole."""

    kind: str
    name: str
    config: dict[str, Any] | None = None
    parents: tuple[ParentLike, ...] = ()
    library_versions: dict[str, str | None] | None = None
    flow_run_id: str | None = None
    task_run_id: str | None = None
    parent_hashes: ParentHashes | None = None

    @classmethod
    def of(
        cls,
        kind: str,
        name: str,
        config: dict[str, Any] | None,
        parents: Iterable[ParentLike],
        provenance: Mapping[str, Any],
    ) -> "ArtifactMeta":
        """The metadata of a `put_*` call: its positional labels and parents, and its keyword
        `provenance`, refused like a misspelt argument (TypeError naming it) unless it is one of
        PROVENANCE_KEYWORDS."""
        unknown = sorted(set(provenance) - set(PROVENANCE_KEYWORDS))
        if unknown:
            raise TypeError(
                f"unexpected keyword argument {unknown[0]!r}: artifact metadata keywords are "
                f"{', '.join(PROVENANCE_KEYWORDS)}"
            )
        return cls(kind, name, config, tuple(parents), **provenance)


class FileEntry(BaseModel):
    """One stored file: its hash plus the size and mtime that decide whether a read must re-hash."""

    path: str
    size: int
    sha256: str
    mtime_ns: int | None = None

    @field_validator("path")
    @classmethod
    def _no_escape(cls, v: str) -> str:
        return safe_relpath(v)


class ArtifactRecord(BaseModel):
    """The sidecar `<id>.json`: everything needed to describe and verify an artifact without a database.

    Its presence is the commit point: an object directory without it is invisible garbage.
    """

    format: int = SIDECAR_FORMAT
    metadata_sha256: str | None = None
    id: str
    kind: str
    name: str
    layout: Literal["file", "dir"]
    files: list[FileEntry]
    config: dict[str, Any] = Field(default_factory=dict)
    parents: list[ParentRef] = Field(default_factory=list)
    code_version: str = ""
    library_versions: dict[str, str | None] = Field(default_factory=dict)
    created_at: datetime = Field(default_factory=utcnow)
    flow_run_id: str | None = None
    task_run_id: str | None = None

    @field_validator("id")
    @classmethod
    def _full_id(cls, v: str) -> str:
        if not ID_RE.match(v):
            raise ValueError(f"artifact id must be 64 lowercase hex characters, got {v!r}")
        return v

    @property
    def size(self) -> int:
        return sum(f.size for f in self.files)

    @property
    def sealed(self) -> bool:
        """Whether the sidecar carried a seal (it matched, or the record would not have been read)."""
        return self.metadata_sha256 is not None


class SealBroken(ValueError):
    """A sidecar whose metadata no longer matches its seal, or whose seal was removed."""


def metadata_digest(doc: dict[str, Any]) -> str:
    """The seal of a sidecar: sha256 of its canonical JSON, without the seal itself and without the
    files' `mtime_ns` (bookkeeping that reads refresh). Everything else is covered: kind, name,
    layout, files (paths, sizes, hashes: what ties the id to the content), config, parents with their
    roles and attrs, code and library versions, creation time and run ids.

    Computed on the parsed JSON document, not the pydantic model, so it does not depend on how a
    value round-trips through the model (defaults, coercions) or on whitespace and key order."""
    body = {k: v for k, v in doc.items() if k != SEAL_FIELD}
    files = body.get("files")
    if isinstance(files, list):
        body["files"] = [
            {k: v for k, v in f.items() if k != "mtime_ns"} if isinstance(f, dict) else f for f in files
        ]
    return hashlib.sha256(canonical_json(body)).hexdigest()


def seal_sidecar(record: ArtifactRecord) -> tuple[ArtifactRecord, bytes]:
    """The record with its seal set, and the sidecar bytes to write (the sealed JSON document)."""
    doc = json.loads(record.model_dump_json())
    doc.pop(SEAL_FIELD, None)
    doc["format"] = SIDECAR_FORMAT
    doc[SEAL_FIELD] = metadata_digest(doc)
    sealed = record.model_copy(update={"format": SIDECAR_FORMAT, "metadata_sha256": doc[SEAL_FIELD]})
    return sealed, json.dumps(doc, indent=1, ensure_ascii=False).encode()


def parse_sidecar(data: bytes | str) -> ArtifactRecord:
    """Read a sidecar, checking its seal first: SealBroken when an edit broke it or removed it,
    ValueError when it is not a sidecar at all. A format-1 sidecar (no seal) is read as unsealed."""
    doc = json.loads(data)
    if not isinstance(doc, dict):
        raise ValueError("a sidecar is a JSON object")
    seal, fmt = doc.get(SEAL_FIELD), doc.get("format", 1)
    if seal is None:
        if not isinstance(fmt, int) or fmt >= 2:
            raise SealBroken(f"its seal {SEAL_FIELD} was removed (a format-{fmt} sidecar carries one)")
    elif seal != metadata_digest(doc):
        raise SealBroken(f"its metadata does not hash to its seal {SEAL_FIELD}={str(seal)[:12]}…")
    return ArtifactRecord.model_validate(doc)


class IntegrityVerdict(BaseModel):
    """What `capvector verify` found for one artifact.

    status: `ok` (sealed sidecar, every byte hashes to the id); `unsealed` (content ok, sidecar from
    before sealing, so its metadata is unprotected); `corrupt` (content or sidecar fails; `detail`
    says which); `missing` (no such artifact); `mismatch` (content and seal ok, but the catalogue
    recorded other metadata at registration: a re-sealed edit, or a deliberate re-registration
    that a catalogue rebuild has not seen yet)."""

    id: str
    status: Literal["ok", "unsealed", "corrupt", "missing", "mismatch"]
    detail: str = ""
    size: int = 0

    @property
    def bad(self) -> bool:
        return self.status in ("corrupt", "missing", "mismatch")


class RunRecord(BaseModel):
    """A flow run as the catalogue's `runs` table sees it; kept in the store (runs/<id>.json) for rebuild."""

    flow_run_id: str
    flow_name: str
    parameters: dict[str, Any] = Field(default_factory=dict)
    state: str = "RUNNING"
    started_at: datetime | None = None
    ended_at: datetime | None = None


class Episode(BaseModel):
    """One evaluation episode; unknown fields are kept and land in the `extras` JSON column."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)
    task: str
    seed: int
    success: bool
    steps: int
    return_: float = Field(alias="return")


class EvaluationDoc(BaseModel):
    """Content of a `kind="evaluation"` artifact; the catalogue's eval tables are derived from it.

    Its episodes are the only record of its scores: readers get them from the catalogue
    (capvector.artifacts.scores), and the sidecar carries none (older sidecars' copies are never read).

    Only what the checkpoint, the protocol and the library versions determine, so the same evaluation
    has the same id wherever and whenever it runs. When it ran is provenance: the sidecar's
    `created_at`. `evaluated_at` is read from documents written before (never written: excluded)."""

    checkpoint_id: str
    fingerprint: str
    library_versions: dict[str, str | None] = Field(default_factory=dict)
    evaluated_at: datetime | None = Field(default=None, exclude=True)
    episodes: list[Episode]


class TensorStat(BaseModel):
    """Statistics of one tensor of a vector; extra numeric columns are kept in `extras`."""

    model_config = ConfigDict(extra="allow")
    tensor: str
    group: str | None = None
    numel: int | None = None
    l2: float | None = None
    rel_norm: float | None = None
    cosine_ref: float | None = None
    sign_agreement: float | None = None


class VectorStatsDoc(BaseModel):
    """Content of a `kind="vector_stats"` artifact (a child of the vector with role `stats_of`).

    `base_id` / `reference_id`: the registered checkpoint the relative norms divide by and the vector
    the cosines compare with, when they are registered; part of the content, so the same vector
    measured against two references gives two artifacts, each with its own lineage."""

    vector_id: str
    tensors: list[TensorStat]
    base_id: str | None = None
    reference_id: str | None = None


class SpectrumRow(BaseModel):
    """The spectrum of one 2-D tensor of an update: its shape, the ranks holding 50 / 90 / 99 % of its
    energy (squared singular values), its largest singular value and all of them, largest first."""

    tensor: str
    kind: str  # module kind: attention, mlp, encoder, action_head or other
    rows: int
    cols: int
    full_rank: int
    rank50: int
    rank90: int
    rank99: int
    top: float
    singular_values: list[float]


class VectorSpectrumDoc(BaseModel):
    """Content of a `kind="vector_spectrum"` artifact: the spectrum of each 2-D tensor of the update
    `vector_id − subtrahend_id` (B − A), or of the vector `vector_id` itself without a subtrahend. A
    child of both (roles `spectrum_of` and `subtrahend`); the ids are part of the content, so the same
    difference of other checkpoints is another artifact, each with its own lineage."""

    vector_id: str
    subtrahend_id: str | None = None
    tensors: list[SpectrumRow]


class LineageRow(BaseModel):
    """One ancestor or descendant: depth counts edges from the start; roles read from the start outwards."""

    id: str
    kind: str | None
    name: str | None
    depth: int
    roles: list[str]
    path: list[str]


class MergedVector(BaseModel):
    """A vector merged into the artifact or one of its ancestors, with the edge's alpha when recorded."""

    vector_id: str
    vector_name: str | None
    merged_into: str
    depth: int
    alpha: float | None
    attrs: dict[str, Any]


class ScoreRow(BaseModel):
    """A per-task score of a checkpoint at `depth` edges below the queried artifact."""

    checkpoint_id: str
    checkpoint_name: str | None
    depth: int
    task: str
    success_rate: float
    n_episodes: int
    fingerprint: str
    evaluation_id: str
    evaluated_at: datetime
