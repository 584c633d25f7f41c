"""DuckDB catalogue: an index over the store (rebuildable from it) answering lineage and score questions.

DuckDB lets one process hold a database file at a time, and readers block while a writer has it
(shared/reference/environment.md §6). So nothing keeps a connection open: every unit of work
connects, does its work in one short transaction, and closes; a lock conflict is retried with
exponential backoff and jitter up to a bounded total wait, then reported as CatalogueBusy.
"""

import json
import random
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar

import duckdb
import pandas as pd
from pydantic import BaseModel

from artifacts.errors import CatalogueBusy, CorruptArtifact, MixedFingerprints
from artifacts.readonly_sql import READ_ONLY_CONFIG, check_read_only
from artifacts.records import (
    ArtifactRecord,
    EvaluationDoc,
    LineageRow,
    MergedVector,
    RunRecord,
    ScoreRow,
    VectorStatsDoc,
)
from artifacts.schema import DATA_TABLES, MIGRATIONS, check_version, migrate

EVALUATION_KIND = "evaluation"
VECTOR_STATS_KIND = "vector_stats"
T = TypeVar("T")
# DuckDB refuses a second connection to a file that one thread of this process holds with another
# configuration (read-only vs read-write), so threads of one process take turns per file.
_PROCESS_LOCKS: dict[str, threading.Lock] = {}
_PROCESS_LOCKS_GUARD = threading.Lock()


def _process_lock(path: Path) -> threading.Lock:
    key = str(path.resolve())
    with _PROCESS_LOCKS_GUARD:
        return _PROCESS_LOCKS.setdefault(key, threading.Lock())


Doc = EvaluationDoc | VectorStatsDoc | None

# Writes are a few rows: one thread halves the cost of opening the file (no worker pool to start).
WRITE_CONFIG = {"threads": 1}
# Integer columns that may hold NULL: pandas would turn them into float64, so they get "Int64".
INT_COLUMNS = {"size_bytes", "n_files", "numel", "episode", "seed", "steps", "n_episodes"}

_WALK = """
WITH RECURSIVE walk(id, depth, via, role) USING KEY (id) AS (
    SELECT e.{far}, 1, e.{near}, e.role FROM edges e WHERE e.{near} = $start
    UNION
    SELECT e.{far}, w.depth + 1, e.{near}, e.role
    FROM walk w JOIN edges e ON e.{near} = w.id
    WHERE w.depth < $max_depth AND e.{far} NOT IN (SELECT id FROM recurring.walk)
), nodes AS (SELECT $start AS id, 0 AS depth UNION ALL SELECT id, depth FROM walk)
"""
# Breadth-first with a visited set (`recurring.walk`): each node is reached once, at its smallest
# depth, so a diamond-shaped history costs one row per node rather than one per path. Each row keeps
# only the hop it came by (`via`, `role`); role paths are rebuilt from those hops in Python, because
# carrying lists through the recursion made the query 6x slower on 10,000 artifacts.
ANCESTORS = _WALK.format(near="child", far="parent")
DESCENDANTS = _WALK.format(near="parent", far="child")

LINEAGE_SELECT = """
SELECT w.id, a.kind, a.name, w.depth, w.via, w.role
FROM walk w LEFT JOIN artifacts a USING (id) ORDER BY w.depth, w.id
"""
VECTORS_SELECT = """
SELECT e.parent, a.name, e.child, n.depth + 1, TRY_CAST(e.attrs->>'alpha' AS DOUBLE), e.attrs
FROM nodes n JOIN edges e ON e.child = n.id AND e.role = 'vector'
LEFT JOIN artifacts a ON a.id = e.parent ORDER BY 4, 1, 3
"""
SCORES_SELECT = """
SELECT t.checkpoint_id, a.name, n.depth, t.task, t.success_rate, t.n_episodes, t.fingerprint,
       t.evaluation_id, t.evaluated_at
FROM nodes n JOIN eval_tasks t ON t.checkpoint_id = n.id LEFT JOIN artifacts a ON a.id = t.checkpoint_id
WHERE $fingerprint IS NULL OR t.fingerprint = $fingerprint
ORDER BY n.depth, t.checkpoint_id, t.task, t.evaluated_at
"""


def _json(value: Any) -> str | None:
    return json.dumps(value, sort_keys=True, default=str) if value else None


def load_doc(store: Any, record: ArtifactRecord) -> Doc:
    """The indexed content of evaluation and vector-stats artifacts (read and hash-checked from the store)."""
    if record.kind == EVALUATION_KIND:
        return EvaluationDoc.model_validate(store.open_json(record.id))
    if record.kind == VECTOR_STATS_KIND:
        return VectorStatsDoc.model_validate(store.open_json(record.id))
    return None


def rows_for(record: ArtifactRecord, doc: Doc = None) -> dict[str, list[dict[str, Any]]]:
    """Catalogue rows derived from one artifact: the single mapping from store to index."""
    rows: dict[str, list[dict[str, Any]]] = {t: [] for t in DATA_TABLES}
    rows["artifacts"].append(
        dict(
            id=record.id,
            kind=record.kind,
            name=record.name,
            layout=record.layout,
            size_bytes=record.size,
            n_files=len(record.files),
            config=_json(record.config),
            code_version=record.code_version,
            library_versions=_json(record.library_versions),
            created_at=record.created_at,
            flow_run_id=record.flow_run_id,
            task_run_id=record.task_run_id,
        )
    )
    for p in record.parents:
        rows["edges"].append(dict(parent=p.id, child=record.id, role=p.role, attrs=_json(p.attrs)))
    if isinstance(doc, EvaluationDoc):
        common = dict(
            evaluation_id=record.id,
            checkpoint_id=doc.checkpoint_id,
            fingerprint=doc.fingerprint,
            library_versions=_json(doc.library_versions),
            evaluated_at=doc.evaluated_at,
        )
        by_task: dict[str, list] = {}
        for i, ep in enumerate(doc.episodes):
            rows["eval_episodes"].append(
                dict(
                    common,
                    episode=i,
                    task=ep.task,
                    seed=ep.seed,
                    success=ep.success,
                    steps=ep.steps,
                    extras=_json(ep.model_extra),
                    **{"return": ep.return_},
                )
            )
            by_task.setdefault(ep.task, []).append(ep)
        for task, eps in by_task.items():
            n = len(eps)
            rows["eval_tasks"].append(
                dict(
                    common,
                    task=task,
                    n_episodes=n,
                    success_rate=sum(e.success for e in eps) / n,
                    mean_return=sum(e.return_ for e in eps) / n,
                    mean_steps=sum(e.steps for e in eps) / n,
                )
            )
    elif isinstance(doc, VectorStatsDoc):
        for t in doc.tensors:
            rows["vector_stats"].append(
                dict(
                    stats_id=record.id,
                    vector_id=doc.vector_id,
                    tensor=t.tensor,
                    group=t.group,
                    numel=t.numel,
                    l2=t.l2,
                    rel_norm=t.rel_norm,
                    cosine_ref=t.cosine_ref,
                    sign_agreement=t.sign_agreement,
                    extras=_json(t.model_extra),
                )
            )
    return rows


def run_row(run: RunRecord) -> dict[str, Any]:
    return dict(
        flow_run_id=run.flow_run_id,
        flow_name=run.flow_name,
        parameters=_json(run.parameters),
        state=run.state,
        started_at=run.started_at,
        ended_at=run.ended_at,
    )


class RebuildReport(BaseModel):
    """What a rebuild indexed, and which artifacts it skipped because they failed verification."""

    artifacts: int
    runs: int
    corrupt: list[str]
    seconds: float


class Catalogue:
    """The catalogue file plus the retrying connection discipline every reader and writer goes through."""

    def __init__(
        self,
        path: str | Path,
        *,
        max_wait_s: float = 30.0,
        migrations: Sequence[tuple[int, str]] = MIGRATIONS,
    ):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.max_wait_s = max_wait_s
        self.retries = 0  # lock conflicts met by this object, for tests and benchmarks
        self._retrying(lambda: self._migrate(migrations))

    def _migrate(self, migrations: Sequence[tuple[int, str]]) -> None:
        con = duckdb.connect(str(self.path))
        try:
            migrate(con, str(self.path), migrations)
        finally:
            con.close()

    # ---------------------------------------------------------------- connections
    def _retrying(self, work: Callable[[], T]) -> T:
        """Run `work` (connect → transaction → close), retrying lock and write conflicts with backoff."""
        deadline = time.monotonic() + self.max_wait_s
        delay = 0.005
        lock = _process_lock(self.path)
        while True:
            try:
                with lock:
                    return work()
            except (duckdb.IOException, duckdb.TransactionException) as e:
                if isinstance(e, duckdb.IOException) and "lock" not in str(e).lower():
                    raise
                if time.monotonic() + delay > deadline:
                    raise CatalogueBusy(
                        f"catalogue {self.path} stayed locked for {self.max_wait_s:.0f} s: {e}"
                    ) from e
                self.retries += 1
                time.sleep(random.uniform(delay / 2, delay))
                delay = min(delay * 2, 0.25)

    def _write(self, fn: Callable[[duckdb.DuckDBPyConnection], T]) -> T:
        def work() -> T:
            con = duckdb.connect(str(self.path), config=WRITE_CONFIG)
            try:
                con.execute("BEGIN")
                out = fn(con)
                con.execute("COMMIT")
                return out
            finally:
                con.close()  # an uncommitted transaction is rolled back on close

        return self._retrying(work)

    def _read(self, fn: Callable[[duckdb.DuckDBPyConnection], T]) -> T:
        def work() -> T:
            con = duckdb.connect(str(self.path), read_only=True, config=READ_ONLY_CONFIG)
            try:
                return fn(con)
            finally:
                con.close()

        return self._retrying(work)

    def schema_version(self) -> int:
        return self._read(lambda con: check_version(con, str(self.path), MIGRATIONS))

    # ---------------------------------------------------------------- writing
    @staticmethod
    def _insert(con: duckdb.DuckDBPyConnection, rows: dict[str, list[dict[str, Any]]], verb: str) -> None:
        for table, table_rows in rows.items():
            if not table_rows:
                continue
            df = pd.DataFrame(table_rows)
            for col in INT_COLUMNS.intersection(df.columns):
                df[col] = df[col].astype("Int64")
            con.register("incoming", df)
            con.execute(f"INSERT {verb} INTO {table} BY NAME SELECT * FROM incoming")
            con.unregister("incoming")

    @staticmethod
    def _merge(items: Iterable[dict[str, list[dict[str, Any]]]]) -> dict[str, list[dict[str, Any]]]:
        out: dict[str, list[dict[str, Any]]] = {t: [] for t in DATA_TABLES}
        for rows in items:
            for table, table_rows in rows.items():
                out[table].extend(table_rows)
        return out

    def add(self, record: ArtifactRecord, doc: Doc = None) -> None:
        """Index one artifact (idempotent: rows already present are left as they are)."""
        rows = rows_for(record, doc)
        self._write(lambda con: self._insert(con, rows, "OR IGNORE"))

    def add_many(self, items: Iterable[tuple[ArtifactRecord, Doc]]) -> None:
        """Index many artifacts in one transaction (bulk inserts, one lock acquisition)."""
        rows = self._merge(rows_for(r, d) for r, d in items)
        self._write(lambda con: self._insert(con, rows, "OR IGNORE"))

    def put_run(self, run: RunRecord) -> None:
        rows = {"runs": [run_row(run)]}
        self._write(lambda con: self._insert(con, rows, "OR REPLACE"))

    def _gather(
        self, store: Any, records: Iterator[str]
    ) -> tuple[list[tuple[ArtifactRecord, Doc]], list[str]]:
        items, corrupt = [], []
        for artifact_id in records:
            try:
                record = store.get(artifact_id)
                items.append((record, load_doc(store, record)))
            except (CorruptArtifact, ValueError):
                corrupt.append(artifact_id)
        return items, corrupt

    def rebuild(self, store: Any) -> RebuildReport:
        """Recreate every table from the store alone, in one transaction (readers see old or new, never half).

        The store is read before the lock is taken, so other writers wait only for the inserts.
        Artifacts whose sidecar or indexed content fails its hash are skipped and listed.
        """
        t0 = time.perf_counter()
        items, corrupt = self._gather(store, store.iter_ids())
        runs = [run_row(r) for r in store.iter_runs()]
        rows = self._merge([*(rows_for(r, d) for r, d in items), {"runs": runs}])

        def replace(con: duckdb.DuckDBPyConnection) -> None:
            for table in DATA_TABLES:
                con.execute(f"DELETE FROM {table}")
            self._insert(con, rows, "OR IGNORE")

        self._write(replace)
        return RebuildReport(
            artifacts=len(items), runs=len(runs), corrupt=sorted(corrupt), seconds=time.perf_counter() - t0
        )

    def sync(self, store: Any) -> int:
        """Index artifacts present in the store but missing here (a writer died between sidecar and row)."""
        known = set(
            self._read(lambda con: [r[0] for r in con.execute("SELECT id FROM artifacts").fetchall()])
        )
        items, _ = self._gather(store, (i for i in store.iter_ids() if i not in known))
        if items:
            self.add_many(items)
        return len(items)

    # ---------------------------------------------------------------- lineage
    def _walk(
        self, cte: str, select: str, start: str, max_depth: int | None, extra: dict[str, Any] | None = None
    ) -> list[tuple]:
        params = {
            "start": start,
            "max_depth": max_depth if max_depth is not None else 2**31 - 1,
            **(extra or {}),
        }
        return self._read(lambda con: con.execute(cte + select, params).fetchall())

    def ancestors(self, artifact_id: str, max_depth: int | None = None) -> list[LineageRow]:
        """Everything `artifact_id` was made from, each once at its shortest distance, with the role path."""
        return _with_paths(artifact_id, self._walk(ANCESTORS, LINEAGE_SELECT, artifact_id, max_depth))

    def descendants(self, artifact_id: str, max_depth: int | None = None) -> list[LineageRow]:
        """Everything made (directly or not) from `artifact_id`."""
        return _with_paths(artifact_id, self._walk(DESCENDANTS, LINEAGE_SELECT, artifact_id, max_depth))

    def vectors_merged_into(self, artifact_id: str) -> list[MergedVector]:
        """Vectors merged into the artifact or any of its ancestors (edges with role `vector`)."""
        rows = self._walk(ANCESTORS, VECTORS_SELECT, artifact_id, None)
        return [
            MergedVector(
                vector_id=r[0],
                vector_name=r[1],
                merged_into=r[2],
                depth=r[3],
                alpha=r[4],
                attrs=json.loads(r[5]) if r[5] else {},
            )
            for r in rows
        ]

    def scores(self, artifact_id: str, fingerprint: str | None = None) -> list[ScoreRow]:
        """Per-task scores of the artifact and everything descended from it, under one protocol.

        Without `fingerprint`, rows under several protocols raise MixedFingerprints rather than being
        returned side by side as if comparable.
        """
        rows = self._walk(DESCENDANTS, SCORES_SELECT, artifact_id, None, {"fingerprint": fingerprint})
        fps = sorted({r[6] for r in rows})
        if len(fps) > 1:
            raise MixedFingerprints(fps)
        return [
            ScoreRow(
                checkpoint_id=r[0],
                checkpoint_name=r[1],
                depth=r[2],
                task=r[3],
                success_rate=r[4],
                n_episodes=r[5],
                fingerprint=r[6],
                evaluation_id=r[7],
                evaluated_at=r[8],
            )
            for r in rows
        ]

    # ---------------------------------------------------------------- read-only SQL
    def query(self, sql: str, params: Sequence[Any] | dict[str, Any] | None = None) -> pd.DataFrame:
        """Run one reading statement (see readonly_sql for the guards) and return a DataFrame."""
        check_read_only(sql)
        return self._read(lambda con: con.execute(sql, params).df())


def _with_paths(start: str, rows: list[tuple]) -> list[LineageRow]:
    """Give each row its id path and role path from `start`, extending the path of the hop it came by.

    Rows arrive ordered by depth, so that hop's path is always known already.
    """
    paths: dict[str, tuple[list[str], list[str]]] = {start: ([start], [])}
    out = []
    for artifact_id, kind, name, depth, via, role in rows:
        ids, roles = paths[via]
        paths[artifact_id] = ids_roles = ([*ids, artifact_id], [*roles, role])
        out.append(
            LineageRow(
                id=artifact_id, kind=kind, name=name, depth=depth, path=ids_roles[0], roles=ids_roles[1]
            )
        )
    return out
