"""DuckDB catalogue: an index over the store (rebuildable from it) answering lineage and score questions.

Connections. DuckDB lets one process hold a database file for writing, and a reader's shared lock keeps
writers out too (DuckDB's file locking: one read-write process, or any number of read-only ones).
So nothing keeps the file open: every unit of work opens it, does its work in one short
transaction, and closes it; a lock conflict is retried with exponential backoff and jitter up to a
bounded total wait, then reported as CatalogueBusy. Opening an up-to-date catalogue takes only the
shared lock (the write lock only to create or migrate it). This module's own reads (schema check,
lineage, scores) attach the file read-only to one in-memory DuckDB per process rather than creating
a database each time (see `_attached_read`).

Faults. The catalogue is an index: one that cannot be read (random bytes after a disk fault, a file
written by a DuckDB whose storage version this one cannot read) is moved aside as
`catalogue.duckdb.corrupt-<time>-<pid>`, kept for inspection, and rebuilt from the store, with one
line saying so. On a home this process may not write (a read-only mount, permissions) the catalogue is
copied into a private temporary folder and worked on there: reads work, and nothing in the home is
written.

Long reads. `query` runs arbitrary read-only SQL (`capvector sql`, selections) on the file for at most
DIRECT_READ_S; a statement still running then is interrupted and re-run on a private snapshot, copied
while the shared lock is held (milliseconds), so a query of minutes never holds a registration off for
longer than that. Lineage and score queries are bounded and read the file directly.

Catching up. The store is the truth and this is an index of it: a writer killed between sidecar and
row, a registration that met a locked catalogue, or a deleted catalogue.duckdb leave it behind. `sync`
indexes what the store has and this lacks (reading only the missing sidecars); `catch_up`, run when an
ArtifactsAPI opens, calls it only when the store may have changed since the last sync: a local store's
fingerprint is the times of its directories (objects/, each objects/<shard>/, runs/), which move
whenever a sidecar or run record is written or removed; about 1 ms for 10,000 artifacts. A fingerprint
is recorded only once every one of those times is SETTLE_NS old, since a coarse filesystem clock could
give a change made right after the listing the same time. A remote store has no directory times: every
commit rewrites its change token (`changes`, one small object), read before listing; a store no writer
has given a token is listed at most every REMOTE_SYNC_INTERVAL_S. Missing sidecars are read
SIDECAR_READERS at a time (a remote read is a round trip: ~30 ms each, one after another).
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import hashlib
import itertools
import json
import logging
import os
import random
import shutil
import tempfile
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, TypeVar

import duckdb
from pydantic import BaseModel, Field

from capvector.artifacts.errors import ArtifactNotFound, CatalogueBusy, CorruptArtifact, MixedFingerprints
from capvector.artifacts.readonly_sql import READ_ONLY_CONFIG, check_read_only
from capvector.artifacts.records import (
    ArtifactRecord,
    EvaluationDoc,
    LineageRow,
    MergedVector,
    RunRecord,
    ScoreRow,
    VectorSpectrumDoc,
    VectorStatsDoc,
    utcnow,
)
from capvector.artifacts.schema import ARTIFACT_COLUMNS, DATA_TABLES, MIGRATIONS, check_version, migrate

if TYPE_CHECKING:  # pandas only where a DataFrame is made: the read-only CLI commands never import it
    import pandas as pd

log = logging.getLogger(__name__)

EVALUATION_KIND = "evaluation"
VECTOR_STATS_KIND = "vector_stats"
VECTOR_SPECTRUM_KIND = "vector_spectrum"
T = TypeVar("T")
# DuckDB refuses a second connection to a file that one thread of this process holds with another
# configuration (read-only vs read-write), so threads of one process take turns per file.
_PROCESS_LOCKS: dict[str, threading.Lock] = {}
_PROCESS_LOCKS_GUARD = threading.Lock()

# A store fingerprint is trusted once its newest directory time is this old (coarse clocks: NFS, FAT).
SETTLE_NS = 2 * 10**9
REMOTE_SYNC_INTERVAL_S = 60.0
# Parallel sidecar reads of a remote catch-up (threads: each read waits on a network round trip).
SIDECAR_READERS_DEFAULT = 16
SIDECAR_READERS = SIDECAR_READERS_DEFAULT
SNAPSHOT_PREFIX = ".snapshot-"
# A read-only query still running after this long moves to a snapshot (see `query`).
DIRECT_READ_S = 0.25


def _process_lock(path: Path) -> threading.Lock:
    key = str(path.resolve())
    with _PROCESS_LOCKS_GUARD:
        return _PROCESS_LOCKS.setdefault(key, threading.Lock())


Doc = EvaluationDoc | VectorStatsDoc | VectorSpectrumDoc | None
# The kinds whose content the catalogue indexes, and the model each is read as.
INDEXED_DOCS: dict[str, type[BaseModel]] = {
    EVALUATION_KIND: EvaluationDoc,
    VECTOR_STATS_KIND: VectorStatsDoc,
    VECTOR_SPECTRUM_KIND: VectorSpectrumDoc,
}

# A migration's own connection: one thread halves the cost of opening the file (no worker pool).
WRITE_CONFIG = {"threads": 1}
# Integer columns that may hold NULL: pandas would turn them into float64, so they get "Int64".
INT_COLUMNS = {"size_bytes", "n_files", "numel", "episode", "seed", "steps", "n_episodes"}

# Creating a DuckDB database costs 20-40 ms (every built-in function is registered anew), attaching a
# file to a running one about 2 ms. So the lookups this module runs itself (schema check, lineage,
# scores, cache keys) and its writes attach the catalogue to one in-memory database per process, and
# detach it when done: no lock outlives the unit of work, as with a connection of its own. Arbitrary
# SQL (`query`) keeps a connection of its own with all of readonly_sql's guards.
_HOST: tuple[int, duckdb.DuckDBPyConnection] | None = None
_HOST_GUARD = threading.Lock()
_ALIASES = itertools.count()


def _host_cursor() -> duckdb.DuckDBPyConnection:
    global _HOST
    with _HOST_GUARD:
        if _HOST is None or _HOST[0] != os.getpid():  # a forked child must not share its parent's
            _HOST = (os.getpid(), duckdb.connect(":memory:", config={"threads": 1}))
        return _HOST[1].cursor()


@atexit.register
def _close_host() -> None:
    """Closed before the interpreter tears down, or DuckDB's bindings report it as leaked."""
    global _HOST
    with _HOST_GUARD:
        if _HOST is not None and _HOST[0] == os.getpid():
            _HOST[1].close()
        _HOST = None


@contextlib.contextmanager
def _attached(path: Path, read_only: bool) -> Iterator[duckdb.DuckDBPyConnection]:
    """A cursor whose default database is `path`, attached to the process's in-memory database for the
    block only: no DuckDB database of its own (creating one costs 20-40 ms of CPU, attaching about 2 ms),
    and the file's lock is held from the attach to the detach, as a connection would hold it."""
    alias, quoted = f"catalogue_{next(_ALIASES)}", str(path).replace("'", "''")
    con = _host_cursor()
    try:
        con.execute(f"ATTACH '{quoted}' AS {alias}{' (READ_ONLY)' if read_only else ''}")
    except BaseException:
        con.close()
        raise
    try:
        con.execute(f"USE {alias}")
        yield con
    finally:
        con.close()  # from another cursor, so that nothing left on this one can keep the file
        detach = _host_cursor()
        try:
            detach.execute(f"DETACH {alias}")
        finally:
            detach.close()


def _attached_read(path: Path, fn: Callable[[duckdb.DuckDBPyConnection], T]) -> T:
    """`fn` on the catalogue at `path`, attached read-only for this call only."""
    with _attached(path, read_only=True) as con:
        return fn(con)


def _attached_write(path: Path, fn: Callable[[duckdb.DuckDBPyConnection], T]) -> T:
    """`fn` in one transaction on the catalogue at `path`, attached read-write for this call only."""
    with _attached(path, read_only=False) as con:
        con.execute("BEGIN")
        try:
            out = fn(con)
            con.execute("COMMIT")
        except BaseException:
            with contextlib.suppress(duckdb.Error):  # a failed COMMIT has rolled back already
                con.execute("ROLLBACK")
            raise
        return out


_WALK = """
WITH RECURSIVE walk(id, depth) USING KEY (id) AS (
    SELECT e.{far}, 1 FROM edges e WHERE e.{near} = $start AND e.{far} <> $start
    UNION
    SELECT e.{far}, w.depth + 1
    FROM walk w JOIN edges e ON e.{near} = w.id
    WHERE w.depth < $max_depth AND e.{far} <> $start AND e.{far} NOT IN (SELECT id FROM recurring.walk)
), nodes AS MATERIALIZED (SELECT $start AS id, 0 AS depth UNION ALL SELECT id, depth FROM walk)
"""
# Breadth-first with a visited set (`recurring.walk`): each node is reached once, at its smallest
# depth, so a diamond-shaped history costs one row per node rather than one per path (and the start
# is never reached again, were the edges ever to hold a cycle). Only (id, depth) is carried: the hop
# each node came by is read from the edges among the walked nodes (below), which the views need anyway.
# MATERIALIZED: the lineage select reads `nodes` twice, and the recursion must run once.
ANCESTORS = _WALK.format(near="child", far="parent")
DESCENDANTS = _WALK.format(near="parent", far="child")

# One row per edge from a walked node (`n`) towards the start (to a child, for ancestors) whose other
# end was walked too: together every edge among the walked nodes, not only the hop each was first
# reached by (history is a DAG: θ_pt is a parent of θ_ft, θ_ao and θ_meta, and views draw all of it).
_LINEAGE_SELECT = """
SELECT n.id, n.depth, a.kind, a.name, e.{near}, e.role
FROM nodes n JOIN edges e ON e.{far} = n.id SEMI JOIN nodes m ON m.id = e.{near}
LEFT JOIN artifacts a ON a.id = n.id
ORDER BY n.depth, n.id, e.{near}, e.role
"""
ANCESTORS_SELECT = ANCESTORS + _LINEAGE_SELECT.format(near="child", far="parent")
DESCENDANTS_SELECT = DESCENDANTS + _LINEAGE_SELECT.format(near="parent", far="child")
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
    """The indexed content of evaluation, vector-stats and vector-spectrum artifacts (read and
    hash-checked from the store)."""
    model = INDEXED_DOCS.get(record.kind)
    return model.model_validate(store.open_json(record.id)) if model is not None else None


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
            sealed=record.sealed,
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
            evaluated_at=doc.evaluated_at or record.created_at,
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
    elif isinstance(doc, VectorSpectrumDoc):
        rows["vector_spectrum"] = _spectrum_rows(record.id, doc)
    return rows


def _spectrum_rows(spectrum_id: str, doc: VectorSpectrumDoc) -> list[dict[str, Any]]:
    """One row per tensor: its ranks and top singular value (the values themselves stay in the store)."""
    common = dict(spectrum_id=spectrum_id, vector_id=doc.vector_id, subtrahend_id=doc.subtrahend_id)
    counts = {"rows", "cols", "full_rank", "rank50", "rank90", "rank99"}
    return [
        dict(
            common,
            tensor=t.tensor,
            module_kind=t.kind,
            top_singular_value=t.top,
            **t.model_dump(include=counts),
        )
        for t in doc.tensors
    ]


def run_row(run: RunRecord) -> dict[str, Any]:
    return dict(
        flow_run_id=run.flow_run_id,
        flow_name=run.flow_name,
        parameters=_json(run.parameters),
        state=run.state,
        started_at=run.started_at,
        ended_at=run.ended_at,
    )


class LineageNode(LineageRow):
    """A lineage row plus `links`, (parent, child, role) triples: every edge between this node and a node of
    the walk on its start side (for ancestors: from this parent to its children in the walk; for
    descendants: from its parents in the walk to it), not only the hop of `path`. Together the rows'
    links are every edge among the walked nodes: history is a DAG, and views draw all of it.

    Plain triples, not models: a model per edge tripled the cost of a 3,000-node lineage."""

    links: list[tuple[str, str, str]] = Field(default_factory=list)


class RebuildReport(BaseModel):
    """What a rebuild indexed, and which artifacts it skipped because they failed verification.

    `unsealed`: artifacts whose sidecar carries no seal (indexed from it only when the catalogue had no
    row for them); `kept`: artifacts whose catalogue rows were kept instead of their sidecar (unsealed
    or failing verification: a row written from a sealed sidecar at registration is worth more)."""

    artifacts: int
    runs: int
    corrupt: list[str]
    seconds: float
    unsealed: list[str] = Field(default_factory=list)
    kept: list[str] = Field(default_factory=list)


class SyncReport(BaseModel):
    """What a sync indexed: artifacts the catalogue lacked, run records it lacked or held in another state."""

    artifacts: int
    runs: int
    corrupt: list[str]
    seconds: float


class VerifyReport(BaseModel):
    """Differences between the store and the catalogue (empty lists: they agree)."""

    objects: int
    rows: int
    rows_without_objects: list[str]
    objects_without_rows: list[str]
    runs_without_rows: list[str]
    rows_without_runs: list[str]

    @property
    def ok(self) -> bool:
        return not (
            self.rows_without_objects
            or self.objects_without_rows
            or self.runs_without_rows
            or self.rows_without_runs
        )


class StoreFingerprint(NamedTuple):
    value: str
    settled: bool


def store_key(store: Any) -> str:
    return os.path.realpath(store.root) if store.local else store.url


def store_fingerprint(store: Any) -> StoreFingerprint | None:
    """The times of a local store's directories: they move whenever a sidecar or a run record is written,
    replaced or removed (each is a rename in objects/<shard>/ or runs/). A remote store: its change
    token (one small read; ArtifactStore._note_change), None where no writer has set one yet (then a
    listing every REMOTE_SYNC_INTERVAL_S is all there is).

    ctime as well as mtime: copies and restores can set a directory's mtime back, never its ctime.
    Settled: every time is SETTLE_NS older than the clock when the stat began."""
    if not store.local:
        token = store.change_token()
        return None if token is None else StoreFingerprint(f"token {token}", True)
    now = time.time_ns()
    root = Path(store.root)
    digest = hashlib.sha256(str(root).encode())
    newest = 0

    def add(name: str, st: os.stat_result) -> None:
        nonlocal newest
        digest.update(f"{name} {st.st_ino} {st.st_mtime_ns} {st.st_ctime_ns}\n".encode())
        newest = max(newest, st.st_mtime_ns, st.st_ctime_ns)

    for sub in ("objects", "runs"):
        try:
            add(sub, os.stat(root / sub))
        except FileNotFoundError:
            digest.update(f"{sub} -\n".encode())
    try:
        shards = sorted((e.name, e.stat()) for e in os.scandir(root / "objects") if e.is_dir())
    except FileNotFoundError:
        shards = []
    for name, st in shards:
        add(f"objects/{name}", st)
    return StoreFingerprint(digest.hexdigest(), newest < now - SETTLE_NS)


def _read_markers(con: duckdb.DuckDBPyConnection) -> dict[str, tuple[str | None, datetime]]:
    try:
        rows = con.execute("SELECT store, fingerprint, synced_at FROM store_sync").fetchall()
    except duckdb.CatalogException:  # a schema from before version 2 (a test's own migrations)
        return {}
    return {s: (f, t) for s, f, t in rows}


def _unreadable(e: Exception) -> bool:
    """A DuckDB error that says the file is not a catalogue this DuckDB can read (not a lock, not a
    permission or a full disk, which moving the file aside would not mend)."""
    text = str(e)
    return isinstance(e, duckdb.SerializationException) or any(
        s in text
        for s in (
            "not a valid DuckDB database file",
            "but we can only read versions",
            "Corrupt database file",
            "database file is corrupt",
        )
    )


def _writable(path: Path) -> bool:
    """Whether this process may write the catalogue file (and its WAL beside it). `os.access` asks
    the kernel, so a read-only mount says no even to root; a plain chmod does not stop root."""
    folder_ok = os.access(path.parent, os.W_OK | os.X_OK)
    return folder_ok and (not path.exists() or os.access(path, os.W_OK))


def _private_copy(path: Path) -> Path:
    """A private copy of the catalogue (and its WAL) in a temporary folder removed at exit: on a home
    this process cannot write, catching up, migrating and reading happen there, and nothing in the
    home is written."""
    folder = Path(tempfile.mkdtemp(prefix="capvector-catalogue-"))
    atexit.register(shutil.rmtree, folder, True)
    copy = folder / path.name
    for src, dst in [(path, copy), (path.with_name(path.name + ".wal"), folder / (path.name + ".wal"))]:
        with contextlib.suppress(FileNotFoundError):
            shutil.copyfile(src, dst)
    log.info("catalogue %s is read-only here: working on a private copy, %s", path, copy)
    return copy


def _run_records(store: Any) -> list[RunRecord]:
    """The store's run records; none (logged) when one is unreadable: runs are bookkeeping, and a bad
    file must not keep the artifacts from being indexed (`rebuild` still fails on it)."""
    try:
        return list(store.iter_runs())
    except (ValueError, OSError) as e:
        log.warning("run records not read: %s", e)
        return []


def _run_state(row: dict[str, Any]) -> tuple:
    return tuple(
        str(row[k]) if row[k] is not None else None
        for k in ("flow_name", "parameters", "state", "started_at", "ended_at")
    )


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
        # The catalogue in the home, when `path` is a private copy of it (a home this process may
        # not write: see `_private_copy`).
        self.home_path: Path | None = None
        # Set when an unreadable file was moved aside: the caller rebuilds it from the store.
        self.needs_rebuild = False
        if not _writable(self.path):
            self.home_path, self.path = self.path, _private_copy(self.path)
        self.max_wait_s = max_wait_s
        self.retries = 0  # lock conflicts met by this object, for tests and benchmarks
        self.migrations = list(migrations)
        # store -> (fingerprint, synced_at) as of the last open or sync by this object
        self.markers: dict[str, tuple[str | None, datetime]] = {}
        self._ready = False
        try:
            self._prepare()
        except CatalogueBusy as e:
            log.warning("%s; it will be opened on first use", e)
        except duckdb.Error as e:
            if not _unreadable(e):
                raise
            self._set_aside(e)
            self._prepare()

    def _set_aside(self, error: Exception) -> None:
        """An unreadable catalogue (random bytes from a disk fault, a file from a DuckDB that this one
        cannot read): it is only an index, so it is moved aside for inspection and a fresh one is
        created, to be rebuilt from the store (`needs_rebuild`). One line tells the user."""
        stamp = datetime.now().strftime("%Y%m%dT%H%M%S")
        aside = self.path.with_name(f"{self.path.name}.corrupt-{stamp}-{os.getpid()}")
        wal = self.path.with_name(self.path.name + ".wal")
        os.replace(self.path, aside)
        if wal.exists():
            os.replace(wal, aside.with_name(aside.name + ".wal"))
        reason = " ".join(str(error).split())
        where = self.home_path or self.path
        kept = f"moved to {aside}" if self.home_path is None else "the home is read-only: left as it is"
        log.warning("catalogue %s cannot be read (%s); %s, rebuilding it from the store", where, reason, kept)
        self.needs_rebuild = True

    def _prepare(self) -> None:
        """Check (read-only, shared lock) or create/migrate (write lock) the schema; read the sync markers."""

        def current(con: duckdb.DuckDBPyConnection) -> bool:
            if check_version(con, str(self.path), self.migrations) < self.migrations[-1][0]:
                return False
            self.markers = _read_markers(con)
            return True

        def work() -> None:
            if self.path.exists() and _attached_read(self.path, current):
                return
            con = duckdb.connect(str(self.path), config=WRITE_CONFIG)
            try:
                migrate(con, str(self.path), self.migrations)
                self.markers = _read_markers(con)
            finally:
                con.close()

        self._retrying(work)
        self._ready = True

    # ---------------------------------------------------------------- connections
    def _retrying(self, work: Callable[[], T], max_wait_s: float | None = None) -> T:
        """Run `work` (connect → transaction → close), retrying lock and write conflicts with backoff."""
        wait = self.max_wait_s if max_wait_s is None else max_wait_s
        deadline = time.monotonic() + wait
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
                    raise CatalogueBusy(f"catalogue {self.path} stayed locked for {wait:.1f} s: {e}") from e
                self.retries += 1
                time.sleep(random.uniform(delay / 2, delay))
                delay = min(delay * 2, 0.25)

    @property
    def ready(self) -> bool:
        """Whether the schema was checked (False while the file stayed locked since this object opened)."""
        return self._ready

    def _ensure_ready(self) -> None:
        if not self._ready:
            self._prepare()

    def _write(self, fn: Callable[[duckdb.DuckDBPyConnection], T], max_wait_s: float | None = None) -> T:
        self._ensure_ready()
        return self._retrying(lambda: _attached_write(self.path, fn), max_wait_s)

    def _lookup(self, fn: Callable[[duckdb.DuckDBPyConnection], T]) -> T:
        """`fn` on the catalogue attached read-only to this process's database: for this module's own
        queries (see `_attached_read`)."""
        self._ensure_ready()
        return self._retrying(lambda: _attached_read(self.path, fn))

    def _read(self, fn: Callable[[duckdb.DuckDBPyConnection], T]) -> T:
        """`fn` on a connection of its own with readonly_sql's guards: for SQL that is not ours."""
        self._ensure_ready()

        def work() -> T:
            con = duckdb.connect(str(self.path), read_only=True, config=READ_ONLY_CONFIG)
            try:
                return fn(con)
            finally:
                con.close()

        return self._retrying(work)

    def _snapshot_read(self, fn: Callable[[duckdb.DuckDBPyConnection], T]) -> T:
        """Run `fn` on a private copy of the catalogue: the shared lock is held only while copying.

        The copy is taken under a read-only connection, so no writer is mid-commit; the WAL a crashed
        writer left goes along (DuckDB replays it when the copy is opened)."""
        self._ensure_ready()
        folder = Path(tempfile.mkdtemp(prefix=SNAPSHOT_PREFIX, dir=self.path.parent))
        snapshot = folder / self.path.name
        wal = self.path.with_name(self.path.name + ".wal")

        def copy() -> None:
            con = duckdb.connect(str(self.path), read_only=True, config=READ_ONLY_CONFIG)
            try:
                shutil.copyfile(self.path, snapshot)
                if wal.exists():
                    shutil.copyfile(wal, snapshot.with_name(snapshot.name + ".wal"))
            finally:
                con.close()

        try:
            self._retrying(copy)
            con = duckdb.connect(str(snapshot), read_only=True, config=READ_ONLY_CONFIG)
            try:
                return fn(con)
            finally:
                con.close()
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def schema_version(self) -> int:
        return self._lookup(lambda con: check_version(con, str(self.path), MIGRATIONS))

    # ---------------------------------------------------------------- writing
    @staticmethod
    def _insert(con: duckdb.DuckDBPyConnection, rows: dict[str, list[dict[str, Any]]], verb: str) -> None:
        for table, table_rows in rows.items():
            if not table_rows:
                continue
            import pandas as pd

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
        self.index([(record, doc)])

    def add_many(self, items: Iterable[tuple[ArtifactRecord, Doc]]) -> None:
        """Index many artifacts in one transaction (bulk inserts, one lock acquisition)."""
        self.index(items)

    def put_run(self, run: RunRecord) -> None:
        self.index([], [run])

    def index(
        self,
        items: Iterable[tuple[ArtifactRecord, Doc]],
        runs: Iterable[RunRecord] = (),
        max_wait_s: float | None = None,
    ) -> None:
        """Artifacts (rows already present are kept) and runs (replaced) in one transaction."""
        rows = self._merge(rows_for(r, d) for r, d in items)
        run_rows = {"runs": [run_row(r) for r in runs]}

        def write(con: duckdb.DuckDBPyConnection) -> None:
            self._insert(con, rows, "OR IGNORE")
            self._insert(con, run_rows, "OR REPLACE")

        self._write(write, max_wait_s)

    @staticmethod
    def _gather(store: Any, ids: Iterable[str]) -> tuple[list[tuple[ArtifactRecord, Doc]], list[str]]:
        """Records and indexed documents of `ids`, read and hash-checked; failures listed, not indexed."""

        def read(artifact_id: str) -> tuple[ArtifactRecord, Doc] | str | None:
            try:
                record = store.get(artifact_id)
                return record, load_doc(store, record)
            except ArtifactNotFound:
                return None  # removed since it was listed
            except (CorruptArtifact, ValueError):
                return artifact_id

        ids = list(ids)
        if store.local or len(ids) < 2:
            results = [read(i) for i in ids]
        else:
            with ThreadPoolExecutor(min(SIDECAR_READERS, len(ids))) as pool:
                results = list(pool.map(read, ids))
        items = [r for r in results if isinstance(r, tuple)]
        corrupt = [r for r in results if isinstance(r, str)]
        return items, corrupt

    def _set_marker(self, con: duckdb.DuckDBPyConnection, key: str, fp: StoreFingerprint | None) -> tuple:
        marker = (fp.value if fp is not None and fp.settled else None, utcnow())
        con.execute("INSERT OR REPLACE INTO store_sync VALUES (?, ?, ?)", [key, *marker])
        return marker

    def rebuild(self, store: Any) -> RebuildReport:
        """Recreate every table from the store, in one transaction (readers see old or new, never half).

        The store is read before the lock is taken, so other writers wait only for the inserts.
        Artifacts whose sidecar or indexed content fails its hash are skipped and listed. An unsealed
        sidecar (no seal: its metadata is unprotected) is never trusted over the catalogue: where the
        catalogue has a row for it, that row and its edges are kept, as are the rows of artifacts that
        fail verification; only an artifact the catalogue does not know is indexed from an unsealed
        sidecar (and listed as such).
        """
        t0 = time.perf_counter()
        key, fp = store_key(store), store_fingerprint(store)  # before listing: later commits move it
        items, corrupt = self._gather(store, store.iter_ids())
        runs = [run_row(r) for r in store.iter_runs()]
        unsealed = sorted(r.id for r, _ in items if not r.sealed)
        untrusted = set(unsealed) | set(corrupt)

        def replace(con: duckdb.DuckDBPyConnection) -> tuple:
            known = {r[0] for r in con.execute("SELECT id FROM artifacts").fetchall()}
            keep = sorted(untrusted & known)
            for table in ("runs", "store_sync"):
                con.execute(f"DELETE FROM {table}")
            for table, column in ARTIFACT_COLUMNS.items():
                con.execute(
                    f"DELETE FROM {table} WHERE {column} NOT IN (SELECT unnest(?::VARCHAR[]))", [keep]
                )
            trusted = [rows_for(r, d) for r, d in items if r.id not in keep]
            self._insert(con, self._merge([*trusted, {"runs": runs}]), "OR IGNORE")
            kept[:] = keep
            return self._set_marker(con, key, fp)

        kept: list[str] = []
        self.markers = {key: self._write(replace)}
        if kept:
            log.warning("catalogue rows kept over unsealed or failing sidecars: %s", ", ".join(kept))
        return RebuildReport(
            artifacts=len(items) - len(set(kept) & set(unsealed)),
            runs=len(runs),
            corrupt=sorted(corrupt),
            seconds=time.perf_counter() - t0,
            unsealed=unsealed,
            kept=kept,
        )

    def recorded_sealed(self, artifact_id: str) -> bool | None:
        """Whether the sidecar this catalogue indexed for `artifact_id` was sealed (None: no row, or a
        row from before the catalogue recorded it)."""
        rows = self._lookup(
            lambda con: con.execute("SELECT sealed FROM artifacts WHERE id = ?", [artifact_id]).fetchall()
        )
        return rows[0][0] if rows else None

    def cached_result(self, cache_key: str) -> str | None:
        """The newest artifact recorded as the result of the step with `cache_key`, or None."""
        rows = self._lookup(
            lambda con: con.execute(
                "SELECT id FROM artifacts WHERE json_extract_string(config, '$.cache_key') = ? "
                "ORDER BY created_at DESC LIMIT 1",
                [cache_key],
            ).fetchall()
        )
        return str(rows[0][0]) if rows else None

    def known(self, artifact_ids: Sequence[str]) -> set[str]:
        """Those of `artifact_ids` that have a row."""
        if not artifact_ids:
            return set()
        rows = self._lookup(
            lambda con: con.execute(
                "SELECT id FROM artifacts WHERE list_contains(?::VARCHAR[], id)", [list(artifact_ids)]
            ).fetchall()
        )
        return {r[0] for r in rows}

    def _indexed(self) -> tuple[set[str], dict[str, tuple]]:
        def read(con: duckdb.DuckDBPyConnection) -> tuple[set[str], dict[str, tuple]]:
            ids = {r[0] for r in con.execute("SELECT id FROM artifacts").fetchall()}
            runs = con.execute(
                "SELECT flow_run_id, flow_name, parameters, state, started_at, ended_at FROM runs"
            ).fetchall()
            keys = ("flow_name", "parameters", "state", "started_at", "ended_at")
            return ids, {r[0]: _run_state(dict(zip(keys, r[1:], strict=True))) for r in runs}

        return self._lookup(read)

    def sync(self, store: Any, max_wait_s: float | None = None) -> SyncReport:
        """Index what the store has and the catalogue lacks: artifacts without a row (only their sidecars
        are read) and run records without a row or in another state; then record the store's fingerprint.
        `max_wait_s` bounds the wait for the lock when there is something to index."""
        t0 = time.perf_counter()
        key, fp = store_key(store), store_fingerprint(store)  # before listing: later commits move it
        known, known_runs = self._indexed()
        items, corrupt = self._gather(store, (i for i in store.iter_ids() if i not in known))
        runs = [r for r in _run_records(store) if _run_state(run_row(r)) != known_runs.get(r.flow_run_id)]
        if corrupt:
            log.warning("not indexed, failed verification: %s", ", ".join(sorted(corrupt)))
        settled = fp.value if fp is not None and fp.settled else None
        old = self.markers.get(key)
        # Nothing new and a fingerprint that cannot be trusted yet: no write (the next open lists again).
        # A remote store records the time of its listing.
        if items or runs or fp is None or (settled is not None and (old is None or old[0] != settled)):
            rows = self._merge(rows_for(r, d) for r, d in items)
            run_rows = {"runs": [run_row(r) for r in runs]}

            def write(con: duckdb.DuckDBPyConnection) -> tuple:
                self._insert(con, rows, "OR IGNORE")
                self._insert(con, run_rows, "OR REPLACE")
                return self._set_marker(con, key, fp)

            if items or runs:
                self.markers[key] = self._write(write, max_wait_s)
            else:  # only the marker: worth one attempt, never a wait (the next open lists again)
                try:
                    self.markers[key] = self._write(write, 0.0)
                except CatalogueBusy:
                    pass
        return SyncReport(
            artifacts=len(items), runs=len(runs), corrupt=sorted(corrupt), seconds=time.perf_counter() - t0
        )

    def needs_sync(self, store: Any) -> bool:
        """Whether the store may hold something this catalogue lacks (cheap: no listing, no sidecar)."""
        marker = self.markers.get(store_key(store))
        if marker is None:
            return True
        fp = store_fingerprint(store)
        if fp is not None:
            return marker[0] != fp.value
        return (utcnow() - marker[1]).total_seconds() >= REMOTE_SYNC_INTERVAL_S

    def catch_up(self, store: Any, max_wait_s: float | None = None) -> SyncReport | None:
        """`sync` when the store may have changed since the last one, else nothing (None)."""
        self._ensure_ready()
        return self.sync(store, max_wait_s) if self.needs_sync(store) else None

    # ---------------------------------------------------------------- store vs catalogue
    def verify(self, store: Any) -> VerifyReport:
        """Rows without a committed artifact, and committed artifacts without a row (runs likewise).

        The catalogue is read before and after the store is listed, so an artifact committed (sidecar,
        then row) while this runs is reported by neither list."""
        before, runs_before = self._indexed()
        objects = set(store.iter_ids())
        run_ids = {r.flow_run_id for r in store.iter_runs()}
        after, runs_after = self._indexed()
        return VerifyReport(
            objects=len(objects),
            rows=len(after),
            rows_without_objects=sorted(before - objects),
            objects_without_rows=sorted(objects - after),
            runs_without_rows=sorted(run_ids - set(runs_after)),
            rows_without_runs=sorted(set(runs_before) - run_ids),
        )

    def remove_rows(self, artifact_ids: Sequence[str], run_ids: Sequence[str] = ()) -> None:
        """Delete the rows derived from artifacts (and run records) that are no longer in the store."""

        def delete(con: duckdb.DuckDBPyConnection) -> None:
            for table, column in ARTIFACT_COLUMNS.items():
                if artifact_ids:
                    con.execute(
                        f"DELETE FROM {table} WHERE {column} IN (SELECT unnest(?))", [list(artifact_ids)]
                    )
            if run_ids:
                con.execute("DELETE FROM runs WHERE flow_run_id IN (SELECT unnest(?))", [list(run_ids)])

        if artifact_ids or run_ids:
            self._write(delete)

    def remove_snapshots(self, older_than_s: float) -> list[str]:
        """Snapshot folders left by readers that were killed mid-query."""
        cutoff, removed = time.time() - older_than_s, []
        for p in self.path.parent.glob(SNAPSHOT_PREFIX + "*"):
            try:
                if p.is_dir() and p.stat().st_mtime <= cutoff:
                    shutil.rmtree(p, ignore_errors=True)
                    removed.append(str(p))
            except FileNotFoundError:
                continue
        return removed

    # ---------------------------------------------------------------- lineage
    def _walk(
        self, sql: str, start: str, max_depth: int | None, extra: dict[str, Any] | None = None
    ) -> list[tuple]:
        params = {
            "start": start,
            "max_depth": max_depth if max_depth is not None else 2**31 - 1,
            **(extra or {}),
        }
        return self._lookup(lambda con: con.execute(sql, params).fetchall())

    def _lineage(self, sql: str, start: str, max_depth: int | None, owner: int) -> list[LineageNode]:
        with _gc_paused():
            return _lineage_nodes(start, self._walk(sql, start, max_depth), owner)

    def ancestors(self, artifact_id: str, max_depth: int | None = None) -> list[LineageNode]:
        """Everything `artifact_id` was made from, each once at its shortest distance, with the role path,
        and (`links`) every edge among them."""
        return self._lineage(ANCESTORS_SELECT, artifact_id, max_depth, owner=0)

    def descendants(self, artifact_id: str, max_depth: int | None = None) -> list[LineageNode]:
        """Everything made (directly or not) from `artifact_id`, with every edge among them (`links`)."""
        return self._lineage(DESCENDANTS_SELECT, artifact_id, max_depth, owner=1)

    def vectors_merged_into(self, artifact_id: str) -> list[MergedVector]:
        """Vectors merged into the artifact or any of its ancestors (edges with role `vector`)."""
        rows = self._walk(ANCESTORS + VECTORS_SELECT, artifact_id, None)
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
        rows = self._walk(DESCENDANTS + SCORES_SELECT, artifact_id, None, {"fingerprint": fingerprint})
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
        """Run one reading statement (see readonly_sql for the guards) and return a DataFrame.

        On the file itself for up to DIRECT_READ_S; a statement still running then is interrupted and
        run again on a private snapshot, so no query holds writers off for longer than that."""
        return self._query(sql, params, lambda result: result.df())

    def query_rows(
        self, sql: str, params: Sequence[Any] | dict[str, Any] | None = None
    ) -> tuple[list[str], list[tuple]]:
        """`query` without pandas: (column names, rows as tuples of Python values)."""
        return self._query(sql, params, lambda res: ([d[0] for d in res.description], res.fetchall()))

    def copy_to(
        self,
        sql: str,
        params: Sequence[Any] | dict[str, Any] | None,
        path: str | os.PathLike[str],
        fmt: str = "parquet",
    ) -> int:
        """Write the rows of one reading statement to `path` with DuckDB's COPY (`fmt`: parquet or csv),
        atomically (a temporary file in the same folder, then a rename); returns the number of rows.

        The guards of `query`, except that this one file may be written: one reading statement, the
        catalogue attached read-only, external access off for any other path, configuration locked. The
        shared lock is held while the file is written (a study's episodes take well under a second)."""
        check_read_only(sql)
        if fmt not in ("parquet", "csv"):
            raise ValueError(f"unknown format {fmt!r}: parquet or csv")
        self._ensure_ready()
        target = Path(path).resolve()
        tmp = target.with_name(f".{target.name}.{os.getpid()}.tmp")
        files = [self.path.resolve(), self.path.resolve().with_name(self.path.name + ".wal"), tmp]

        def quoted(p: Path) -> str:
            return "'" + str(p).replace("'", "''") + "'"

        def work() -> int:
            con = duckdb.connect(":memory:", config={"threads": 1})
            try:
                con.execute(f"SET allowed_paths = [{', '.join(quoted(f) for f in files)}]")
                con.execute("SET enable_external_access = false")
                con.execute("SET lock_configuration = true")
                con.execute(f"ATTACH {quoted(files[0])} AS catalogue (READ_ONLY)")
                con.execute("USE catalogue")
                row = con.execute(f"COPY ({sql}) TO {quoted(tmp)} (FORMAT {fmt})", params).fetchone()
                return int(row[0]) if row else 0
            finally:
                con.close()

        try:
            n = self._retrying(work)
            os.replace(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)
        return n

    def _query(self, sql: str, params: Any, fetch: Callable[[duckdb.DuckDBPyConnection], Any]) -> Any:
        check_read_only(sql)

        def direct(con: duckdb.DuckDBPyConnection) -> Any:
            fired = threading.Event()

            def interrupt() -> None:
                fired.set()
                con.interrupt()

            timer = threading.Timer(DIRECT_READ_S, interrupt)
            timer.start()
            try:
                return fetch(con.execute(sql, params))
            except duckdb.InterruptException:
                if not fired.is_set():
                    raise  # interrupted by someone else (Ctrl-C), not by the timer
                return None
            finally:
                timer.cancel()
                timer.join()  # the connection closes next: no interrupt may reach it after that

        result = self._read(direct)
        if result is None:
            result = self._snapshot_read(lambda con: fetch(con.execute(sql, params)))
        return result


@contextlib.contextmanager
def _gc_paused() -> Iterator[None]:
    """No cycle collection while a lineage is fetched and built. Its tens of thousands of new objects
    (none in a cycle) set off dozens of collections, among them a full pass over every object a fresh
    process's imports left (30-70 ms CPU for 4,580 nodes, more than the build); afterwards one pass over
    the young objects remains."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def _lineage_nodes(start: str, rows: Iterable[tuple], owner: int) -> list[LineageNode]:
    """Nodes from a lineage select's rows, which come ordered by depth, node, near end and role. A node's
    links are its rows' edges (`owner`: the node is the edge's parent (0, ancestors) or child (1)); its
    path extends that of the first of them whose near end is one step nearer the start, so the choice
    among equally short paths does not depend on the query plan.

    Not validated: every value comes from our own schema, and validating 3,000-5,000 nodes cost more
    than the query (pydantic's model_construct is slower still)."""
    paths: dict[str, tuple[list[str], list[str]]] = {start: ([start], [])}
    depths = {start: 0}
    nodes: list[dict[str, Any]] = []
    node: dict[str, Any] = {"id": None}
    for node_id, depth, kind, name, near, role in rows:
        if node_id != node["id"]:
            depths[node_id] = depth
            node = dict(id=node_id, kind=kind, name=name, depth=depth, roles=None, path=None, links=[])
            nodes.append(node)
        node["links"].append((node_id, near, role) if owner == 0 else (near, node_id, role))
        if node["path"] is None and depths.get(near) == depth - 1:
            ids, roles = paths[near]
            path = paths[node_id] = ([*ids, node_id], [*roles, role])
            node["path"], node["roles"] = path
    return [_trusted(LineageNode, node) for node in nodes]


M = TypeVar("M", bound=BaseModel)


def _trusted(cls: type[M], fields: dict[str, Any]) -> M:
    """`cls` from a value for every field, of the right type, unvalidated: what model_construct sets,
    for a model without extras, private attributes or post-init."""
    obj = cls.__new__(cls)
    object.__setattr__(obj, "__dict__", fields)
    object.__setattr__(obj, "__pydantic_fields_set__", set(fields))
    object.__setattr__(obj, "__pydantic_extra__", None)
    object.__setattr__(obj, "__pydantic_private__", None)
    return obj
