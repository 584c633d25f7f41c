"""The one Python entry point that tasks, flows and the CLI share: store + catalogue kept in step.

Order of a registration: content into the store (temp + rename), sidecar (the commit point), then the
catalogue row. The store is the truth, so the catalogue may fall behind it but never the reverse:
- a registration whose row cannot be written (the catalogue stayed locked) still succeeds; the row
  waits in this object and is written before its next read or write, or by the next open's catch-up;
- a process killed between sidecar and row, or a deleted catalogue.duckdb, is caught up when the next
  ArtifactsAPI opens (`Catalogue.catch_up`: a cheap check, then only the missing sidecars are read);
  on a remote store, where catching up a new machine's catalogue lists the whole store, only before
  the object's first catalogue read: a process that only registers, or reads by id (a content-cache
  hit: capvector.tasks.runtime.caching), never lists the store;
- `adopt` indexes artifacts another machine committed by their ids, with the ancestors this catalogue
  lacks, reading their sealed sidecars (no listing): how a driver indexes the ids its steps return;
- `capvector catalogue sync|rebuild|verify|gc` do the same on demand.
"""

import json
import logging
import os
import threading
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import duckdb
from pydantic import BaseModel

from capvector.artifacts import home as home_mod
from capvector.artifacts.catalogue import (
    EVALUATION_KIND,
    VECTOR_SPECTRUM_KIND,
    VECTOR_STATS_KIND,
    Catalogue,
    Doc,
    LineageNode,
    RebuildReport,
    SyncReport,
    VerifyReport,
    load_doc,
)
from capvector.artifacts.errors import (
    ArtifactError,
    ArtifactNotFound,
    CatalogueBusy,
    CorruptArtifact,
    UnknownParent,
)
from capvector.artifacts.records import (
    ArtifactRecord,
    EvaluationDoc,
    MergedVector,
    ParentRef,
    RunRecord,
    ScoreRow,
    SpectrumRow,
    TensorStat,
    VectorSpectrumDoc,
    VectorStatsDoc,
)
from capvector.artifacts.store import ArtifactStore, ParentLike

if TYPE_CHECKING:
    import pandas as pd

log = logging.getLogger(__name__)

# Once a write met a locked catalogue, later writes of the same object wait this long, not max_wait_s:
# their rows are safe in the store, and a step should not stall max_wait_s per registration.
BUSY_WAIT_S = 1.0
# The catch-up at open waits this long for the lock (another process's transaction takes milliseconds,
# a parallel catch-up of a deleted catalogue a second or two), then leaves it to a later open.
CATCH_UP_WAIT_S = 5.0


class GcReport(BaseModel):
    """What `gc` did: store leftovers removed (staging), objects without a sidecar moved to quarantine
    (`quarantined`, their new paths) or kept in place because something names them as a parent
    (`kept`), catalogue rows of artifacts and runs no longer in the store, and snapshot folders of
    killed readers."""

    store: list[str]
    rows: list[str]
    runs: list[str]
    snapshots: list[str]
    quarantined: list[str] = []
    kept: list[str] = []


class ArtifactsAPI:
    """Register artifacts and ask the catalogue about them; ids may be given as unique prefixes.

    `catch_up=False` opens without indexing what the store has and the catalogue lacks (for `verify`,
    which reports the difference rather than repairing it)."""

    def __init__(
        self,
        home: str | os.PathLike[str] | None = None,
        *,
        catalogue_path: str | Path | None = None,
        cache_dir: str | Path | None = None,
        max_wait_s: float = 30.0,
        catch_up: bool = True,
    ):
        self.home = str(home) if home is not None else home_mod.default_home()
        self.store = ArtifactStore(home_mod.store_url(self.home), cache_dir=cache_dir)
        self.catalogue = Catalogue(
            catalogue_path or home_mod.catalogue_path(self.home), max_wait_s=max_wait_s
        )
        self._pending: dict[str, tuple[ArtifactRecord, Doc]] = {}
        self._pending_runs: dict[str, RunRecord] = {}
        self._busy = False
        self._lock = threading.RLock()
        self.store.unsealed_guard = self._refuse_downgrade
        if self.catalogue.needs_rebuild:  # an unreadable catalogue was set aside: the store is the truth
            report = self.catalogue.rebuild(self.store)
            self.catalogue.needs_rebuild = False
            log.debug(
                "catalogue rebuilt from the store: %d artifacts, %d runs", report.artifacts, report.runs
            )
        # A remote store is caught up before the first catalogue read instead (`_read_ready`).
        self._deferred = catch_up and not self.store.local
        if catch_up and self.store.local:
            self.catch_up()

    # ---------------------------------------------------------------- keeping up with the store
    def catch_up(self) -> SyncReport | None:
        """Index what the store has and the catalogue lacks, if the store changed since the last sync.

        Never raises CatalogueBusy: a catalogue that stays locked is caught up by a later open."""
        self._deferred = False
        if not self.catalogue.ready:  # it stayed locked while this object opened it: do not wait again
            self._busy = True
            return None
        try:
            wait = min(BUSY_WAIT_S if self._busy else CATCH_UP_WAIT_S, self.catalogue.max_wait_s)
            report = self.catalogue.catch_up(self.store, wait)
        except CatalogueBusy as e:
            log.warning("%s; not caught up with the store this time", e)
            return None
        except (ArtifactError, OSError, ValueError) as e:  # best effort: an open must not fail on it
            log.warning("catalogue not caught up with the store (%s); see `capvector catalogue sync`", e)
            return None
        if report is not None and (report.artifacts or report.runs):
            log.info(
                "catalogue caught up with the store: %d artifacts, %d runs indexed",
                report.artifacts,
                report.runs,
            )
        return report

    def _refuse_downgrade(self, record: ArtifactRecord) -> None:
        """An unsealed sidecar of an artifact the catalogue indexed from a sealed one: its seal was
        stripped (and `format: 1` written) to edit it. Refused like a broken seal, wherever it is read
        (`show`, `Workspace.path`, a registration naming it as a parent, `verify`, a rebuild).

        Without a readable catalogue nothing is known; a warning says so and the record loads as
        unsealed (as a genuinely old one does)."""
        if record.id in self._pending:
            return
        try:
            sealed = self.catalogue.recorded_sealed(record.id)
        except (ArtifactError, duckdb.Error) as e:
            log.warning("unsealed sidecar of %s not compared with the catalogue (%s)", record.id, e)
            return
        if sealed:
            raise CorruptArtifact(
                record.id,
                "its sidecar carries no seal, but the catalogue recorded it sealed at registration: the "
                "seal was stripped (its kind, name, config and lineage are not trusted; re-run the "
                "computation that produced it to change them)",
            )

    def _read_ready(self) -> None:
        """Before a catalogue read: the deferred catch-up of a remote store (once), then this object's
        pending rows."""
        if self._deferred:
            with self._lock:
                if self._deferred:
                    self.catch_up()
        self._flush()

    def adopt(self, ids: Iterable[str]) -> int:
        """Index artifacts committed elsewhere (another machine's step) by id, without listing the
        store: each one the catalogue lacks, and the ancestors it names that it lacks too, from their
        sealed sidecars. How many were indexed; an id not (or no longer) in the store is skipped."""
        self._flush()
        todo, seen, items = list(dict.fromkeys(ids)), set(), []
        while todo:
            todo = [i for i in todo if i not in seen]
            seen.update(todo)
            missing = sorted(set(todo) - self.catalogue.known(todo))
            todo = []
            for artifact_id in missing:
                try:
                    record = self.store.get(artifact_id)
                    doc = load_doc(self.store, record)
                except ArtifactNotFound:
                    continue
                items.append((record, doc))
                todo.extend(p.id for p in record.parents)
        if items:
            self.catalogue.index(items)
        return len(items)

    @property
    def pending(self) -> int:
        """Artifacts and runs committed to the store whose rows this object has not written yet."""
        return len(self._pending) + len(self._pending_runs)

    def _flush(self) -> None:
        """Write the pending rows; a locked catalogue leaves them pending (their store commit stands)."""
        with self._lock:
            if not self.pending:
                return
            try:
                self.catalogue.index(
                    list(self._pending.values()),
                    list(self._pending_runs.values()),
                    max_wait_s=min(BUSY_WAIT_S, self.catalogue.max_wait_s) if self._busy else None,
                )
            except CatalogueBusy as e:
                if not self._busy:
                    log.warning(
                        "%s; %d registration(s) are committed in the store and will be indexed once it is "
                        "free (or by `capvector catalogue sync`)",
                        e,
                        self.pending,
                    )
                self._busy = True
                return
            except BaseException:
                # Not a lock: rows that cannot be written would fail every later call too. Their store
                # commit stands; `catalogue verify` reports them and a later open retries them.
                self._pending.clear()
                self._pending_runs.clear()
                raise
            self._busy = False
            self._pending.clear()
            self._pending_runs.clear()

    def _index(self, record: ArtifactRecord) -> ArtifactRecord:
        doc = load_doc(self.store, record)
        with self._lock:
            self._pending[record.id] = (record, doc)
            self._flush()
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

    def register_vector_spectrum(
        self,
        vector_id: str,
        tensors: Iterable[SpectrumRow | dict[str, Any]],
        subtrahend_id: str | None = None,
        name: str | None = None,
        **meta: Any,
    ) -> ArtifactRecord:
        """Store the spectrum of each 2-D tensor of `vector_id − subtrahend_id` (of the vector alone
        without a subtrahend) as a child of both (roles `spectrum_of` and `subtrahend`), so a rank
        quoted in a report traces to the checkpoints it was measured on."""
        vector = self.store.get(vector_id)
        subtrahend = self.store.get(subtrahend_id) if subtrahend_id else None
        doc = VectorSpectrumDoc(
            vector_id=vector.id,
            subtrahend_id=subtrahend.id if subtrahend else None,
            tensors=[SpectrumRow.model_validate(t) for t in tensors],
        )
        refs = [(vector.id, "spectrum_of")] + ([(subtrahend.id, "subtrahend")] if subtrahend else [])
        default = f"spectrum of {vector.name}" + (f" - {subtrahend.name}" if subtrahend else "")
        return self.register_json(doc, VECTOR_SPECTRUM_KIND, name or default, None, refs, **meta)

    def record_run(self, run: RunRecord) -> None:
        """Create or update a flow run (store first, so rebuild and sync know it too)."""
        self.store.put_run(run)
        with self._lock:
            self._pending_runs[run.flow_run_id] = run
            self._flush()

    # ---------------------------------------------------------------- read
    def get(self, id_or_prefix: str) -> ArtifactRecord:
        return self.store.get(id_or_prefix)

    def path(self, id_or_prefix: str, verify: bool = True, member: str | None = None) -> Path:
        """The store's `path` (every byte checked against the id unless `verify=False`)."""
        return self.store.path(id_or_prefix, verify=verify, member=member)

    # Reads write this object's pending rows first, so a registration is visible to its own process.
    def ancestors(self, id_or_prefix: str, max_depth: int | None = None) -> list[LineageNode]:
        self._read_ready()
        return self.catalogue.ancestors(self.store.resolve(id_or_prefix), max_depth)

    def descendants(self, id_or_prefix: str, max_depth: int | None = None) -> list[LineageNode]:
        self._read_ready()
        return self.catalogue.descendants(self.store.resolve(id_or_prefix), max_depth)

    def vectors_merged_into(self, id_or_prefix: str) -> list[MergedVector]:
        self._read_ready()
        return self.catalogue.vectors_merged_into(self.store.resolve(id_or_prefix))

    def scores(self, id_or_prefix: str, fingerprint: str | None = None) -> list[ScoreRow]:
        self._read_ready()
        return self.catalogue.scores(self.store.resolve(id_or_prefix), fingerprint)

    def cached_result(self, cache_key: str) -> str | None:
        """The newest artifact the catalogue records as the result of the step with `cache_key`."""
        self._read_ready()
        return self.catalogue.cached_result(cache_key)

    def query(self, sql: str, params: Any = None) -> "pd.DataFrame":
        """Read-only SQL over the catalogue tables (on a snapshot: a long query holds no writer off)."""
        self._read_ready()
        return self.catalogue.query(sql, params)

    def query_rows(self, sql: str, params: Any = None) -> tuple[list[str], list[tuple]]:
        """`query` without pandas: (column names, rows as tuples)."""
        self._read_ready()
        return self.catalogue.query_rows(sql, params)

    def copy_to(self, sql: str, params: Any, path: str | os.PathLike[str], fmt: str = "parquet") -> int:
        """The rows of one reading statement written to `path` (Parquet or CSV, by DuckDB's COPY); how
        many rows."""
        self._read_ready()
        return self.catalogue.copy_to(sql, params, path, fmt)

    # ---------------------------------------------------------------- maintenance
    def rebuild(self) -> RebuildReport:
        """Recreate the catalogue from the store alone."""
        with self._lock:
            report = self.catalogue.rebuild(self.store)
            self._deferred = False
            self._pending.clear()  # the store holds them, so the rebuild indexed them
            self._pending_runs.clear()
            self._busy = False
        return report

    def sync(self) -> SyncReport:
        """Index what the store has and the catalogue lacks (a full listing, whatever the fingerprint)."""
        self._flush()
        self._deferred = False
        return self.catalogue.sync(self.store)

    def verify(self) -> VerifyReport:
        """Rows without objects and objects without rows (artifacts and runs); repairs nothing."""
        self._flush()
        return self.catalogue.verify(self.store)

    def gc(self, older_than_s: float = 3600.0) -> GcReport:
        """The store's gc (staging leftovers removed; objects without a sidecar quarantined, never
        deleted), plus the catalogue rows of artifacts and runs no longer in the store, and stale
        snapshot folders.

        Nothing that the catalogue or any sidecar names as a parent is touched: not its object (left in
        place when its sidecar is lost) and not its row (its kind, name and config may be all that is
        left of its metadata). A quarantined object gets its catalogue row (and edges) written beside
        it (`<id>.catalogue-row.json`) before the row leaves the catalogue."""
        self._flush()
        parents = set(self.query("SELECT DISTINCT parent FROM edges")["parent"].tolist())
        result = self.store.gc(older_than_s, referenced=parents)
        for dest in result.quarantined:
            self._save_row_beside(dest)
        report = self.catalogue.verify(self.store)
        parents |= self.store.referenced_parents()
        gone = [
            i
            for i in report.rows_without_objects
            if i not in parents
            and not self.store.exists(i)
            and not self.store.fs.exists(self.store.object_path(i))
        ]
        run_ids = set(report.rows_without_runs) - {r.flow_run_id for r in self.store.iter_runs()}
        self.catalogue.remove_rows(gone, sorted(run_ids))
        if result.quarantined or result.kept:
            log.warning(
                "gc: %d object(s) without a sidecar moved to quarantine, %d kept as named parents",
                len(result.quarantined),
                len(result.kept),
            )
        return GcReport(
            store=result.removed,
            rows=gone,
            runs=sorted(run_ids),
            snapshots=self.catalogue.remove_snapshots(older_than_s),
            quarantined=result.quarantined,
            kept=result.kept,
        )

    def _save_row_beside(self, dest: str) -> None:
        """The catalogue's row of a quarantined object, written next to it (its only metadata left)."""
        artifact_id = os.path.basename(dest)
        try:
            frame = self.query("SELECT * FROM artifacts WHERE id = ?", [artifact_id])
            edges = self.query("SELECT parent, role, attrs FROM edges WHERE child = ?", [artifact_id])
        except (ArtifactError, duckdb.Error) as e:
            log.warning("catalogue row of quarantined %s not saved: %s", artifact_id, e)
            return
        if frame.empty:
            return
        doc = {"artifact": frame.to_dict(orient="records")[0], "parents": edges.to_dict(orient="records")}
        with self.store.fs.open(dest + ".catalogue-row.json", "w") as f:
            f.write(json.dumps(doc, indent=1, default=str))


def _parent_id(p: ParentLike) -> str:
    return p.id if isinstance(p, ParentRef) else p[0]


def _parent_role(p: ParentLike) -> str:
    return p.role if isinstance(p, ParentRef) else p[1]
