"""Pydantic records: the sidecar of every artifact and the JSON documents the catalogue indexes."""

import posixpath
import re
from datetime import UTC, datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from artifacts.errors import PathEscape

SIDECAR_FORMAT = 1
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
    """Content of a `kind="evaluation"` artifact; the catalogue's eval tables are derived from it."""

    checkpoint_id: str
    fingerprint: str
    library_versions: dict[str, str | None] = Field(default_factory=dict)
    evaluated_at: datetime = Field(default_factory=utcnow)
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
