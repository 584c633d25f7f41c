"""The one Python entry point that tasks, flows and the CLI share: store + catalogue kept in step.

Order of a registration: content into the store (temp + rename), sidecar (the commit point), then the
catalogue row. A crash after the sidecar leaves the catalogue behind the store, which `sync` or
`rebuild` repairs; never the reverse.
"""

import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import pandas as pd

from artifacts import home as home_mod
from artifacts.catalogue import EVALUATION_KIND, VECTOR_STATS_KIND, Catalogue, RebuildReport, load_doc
from artifacts.errors import ArtifactNotFound, UnknownParent
from artifacts.records import (
    ArtifactRecord,
    EvaluationDoc,
    LineageRow,
    MergedVector,
    ParentRef,
    RunRecord,
    ScoreRow,
    TensorStat,
    VectorStatsDoc,
)
from artifacts.store import ArtifactStore, ParentLike


class ArtifactsAPI:
    """Register artifacts and ask the catalogue about them; ids may be given as unique prefixes."""

    def __init__(
        self,
        home: str | os.PathLike[str] | None = None,
        *,
        catalogue_path: str | Path | None = None,
        cache_dir: str | Path | None = None,
        max_wait_s: float = 30.0,
    ):
        self.home = str(home) if home is not None else home_mod.default_home()
        self.store = ArtifactStore(home_mod.store_url(self.home), cache_dir=cache_dir)
        self.catalogue = Catalogue(
            catalogue_path or home_mod.catalogue_path(self.home), max_wait_s=max_wait_s
        )

    def _index(self, record: ArtifactRecord) -> ArtifactRecord:
        self.catalogue.add(record, load_doc(self.store, record))
        return record

    # ---------------------------------------------------------------- register
    def register_file(
        self,
        src: str | os.PathLike[str],
        kind: str,
        name: str,
        config: dict[str, Any] | None = None,
        parents: Iterable[ParentLike] = (),
        **meta: Any,
    ) -> ArtifactRecord:
        """Store a file and index it. `meta`: filename, library_versions, flow_run_id, task_run_id."""
        return self._index(self.store.put_file(src, kind, name, config, parents, **meta))

    def register_dir(
        self,
        src: str | os.PathLike[str],
        kind: str,
        name: str,
        config: dict[str, Any] | None = None,
        parents: Iterable[ParentLike] = (),
        **meta: Any,
    ) -> ArtifactRecord:
        """Store a directory (dataset, sharded checkpoint, adapter) as one artifact and index it."""
        return self._index(self.store.put_dir(src, kind, name, config, parents, **meta))

    def register_json(
        self,
        obj: Any,
        kind: str,
        name: str,
        config: dict[str, Any] | None = None,
        parents: Iterable[ParentLike] = (),
        **meta: Any,
    ) -> ArtifactRecord:
        """Store a JSON document (report, evaluation, stats) and index it."""
        return self._index(self.store.put_json(obj, kind, name, config, parents, **meta))

    def register_evaluation(
        self,
        doc: EvaluationDoc | dict[str, Any],
        name: str,
        config: dict[str, Any] | None = None,
        parents: Iterable[ParentLike] = (),
        **meta: Any,
    ) -> ArtifactRecord:
        """Store an evaluation; the evaluated checkpoint becomes a parent with role `checkpoint`."""
        doc = EvaluationDoc.model_validate(doc)
        try:
            checkpoint = self.store.resolve(doc.checkpoint_id)
        except ArtifactNotFound:
            raise UnknownParent(doc.checkpoint_id) from None
        doc = doc.model_copy(update={"checkpoint_id": checkpoint})
        refs = list(parents)
        if not any(_parent_id(p) == checkpoint and _parent_role(p) == "checkpoint" for p in refs):
            refs.append((checkpoint, "checkpoint"))
        return self.register_json(doc, EVALUATION_KIND, name, config, refs, **meta)

    def register_vector_stats(
        self,
        vector_id: str,
        tensors: Iterable[TensorStat | dict[str, Any]],
        name: str | None = None,
        base_id: str | None = None,
        reference_id: str | None = None,
        **meta: Any,
    ) -> ArtifactRecord:
        """Store per-tensor statistics of a vector as a child artifact (role `stats_of`); a registered
        base (role `base`) and reference vector (role `reference`) become parents too, so a cosine
        quoted in a report traces to both vectors."""
        vector = self.store.get(vector_id)
        base = self.store.resolve(base_id) if base_id else None
        reference = self.store.resolve(reference_id) if reference_id else None
        doc = VectorStatsDoc(
            vector_id=vector.id,
            tensors=[TensorStat.model_validate(t) for t in tensors],
            base_id=base,
            reference_id=reference,
        )
        refs = [(vector.id, "stats_of")] + [
            (i, r) for i, r in [(base, "base"), (reference, "reference")] if i
        ]
        return self.register_json(
            doc, VECTOR_STATS_KIND, name or f"stats of {vector.name}", None, refs, **meta
        )

    def record_run(self, run: RunRecord) -> None:
        """Create or update a flow run (store first, so rebuild knows it too)."""
        self.store.put_run(run)
        self.catalogue.put_run(run)

    # ---------------------------------------------------------------- read
    def get(self, id_or_prefix: str) -> ArtifactRecord:
        return self.store.get(id_or_prefix)

    def path(self, id_or_prefix: str, verify: bool = False, member: str | None = None) -> Path:
        return self.store.path(id_or_prefix, verify=verify, member=member)

    def ancestors(self, id_or_prefix: str, max_depth: int | None = None) -> list[LineageRow]:
        return self.catalogue.ancestors(self.store.resolve(id_or_prefix), max_depth)

    def descendants(self, id_or_prefix: str, max_depth: int | None = None) -> list[LineageRow]:
        return self.catalogue.descendants(self.store.resolve(id_or_prefix), max_depth)

    def vectors_merged_into(self, id_or_prefix: str) -> list[MergedVector]:
        return self.catalogue.vectors_merged_into(self.store.resolve(id_or_prefix))

    def scores(self, id_or_prefix: str, fingerprint: str | None = None) -> list[ScoreRow]:
        return self.catalogue.scores(self.store.resolve(id_or_prefix), fingerprint)

    def query(self, sql: str, params: Any = None) -> pd.DataFrame:
        """Read-only SQL over the catalogue tables."""
        return self.catalogue.query(sql, params)

    # ---------------------------------------------------------------- maintenance
    def rebuild(self) -> RebuildReport:
        return self.catalogue.rebuild(self.store)

    def sync(self) -> int:
        return self.catalogue.sync(self.store)

    def gc(self, older_than_s: float = 3600.0) -> list[str]:
        return self.store.gc(older_than_s)


def _parent_id(p: ParentLike) -> str:
    return p.id if isinstance(p, ParentRef) else p[0]


def _parent_role(p: ParentLike) -> str:
    return p.role if isinstance(p, ParentRef) else p[1]
