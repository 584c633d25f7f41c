"""Keep what runs leave behind bounded: the run logs of a home and Prefect's record of flow runs.

Two things grow with every flow command and nothing else ever removes them:

- **Run logs**: `<home>/logs/<command>-<time>-<pid>.log` (for a remote home, in its local cache
  folder), one per flow command (capvector.flows.cli.main). `prune_logs` deletes the oldest ones beyond an
  age, a count and a total size. It lists only `*.log` files directly in that folder (regular files, links not
  followed), never the log named in $CAPVECTOR_LOG_FILE (the current run's) and never one written to in the
  last `ACTIVE_S` seconds (a run still going): nothing else in the home is ever looked at, so the store, the
  catalogue, the step cache, reports and work folders cannot be touched. `prune_on_start(home)` applies the
  default limits and never fails: a flow command calls it first.
- **Prefect's flow runs**: every flow run, its task runs, their states, logs and UI artifacts stay in
  the database of the Prefect server the run used; with the embedded server that is
  `$PREFECT_HOME/prefect.db` (SQLite; the Makefile sets PREFECT_HOME to `.prefect/`), about 0.35 MB
  per smoke run and 5 MB per `study-smoke`. `prune_prefect_db` deletes finished runs of capvector's
  flows (`CAPVECTOR_FLOWS`) beyond an age or a count **through Prefect's client** (`delete_flow_run`:
  the server removes the run with its task runs and states, and its logs in the background; the run's
  UI artifacts are deleted with `delete_artifact`), so the same call works on the embedded database
  and on a server named by PREFECT_API_URL, under Prefect's own schema and its migrations. On the
  embedded SQLite file it then runs VACUUM, which gives the freed pages back to the disk.

  Why not Prefect's settings alone: its flow-run vacuum (`PREFECT_SERVER_SERVICES_DB_VACUUM_ENABLED=
  flow_runs`, `..._RETENTION_PERIOD`) is a background service that the embedded server, which lives
  for one run, never starts. Its *event* vacuum does run there, at every start: events (the largest
  tables) older than `PREFECT_SERVER_EVENTS_RETENTION_PERIOD` (7 days by default) are deleted by Prefect
  itself, so they are not pruned here. Why not SQL on the file: the schema is Prefect's (it changes
  with its migrations) and a database behind PREFECT_API_URL is not ours to open.

  Without PREFECT_API_URL, Prefect's client starts its embedded server for the call (about 8 to 10 s
  on a busy 2-core machine), which is why pruning runs is a command (`capvector catalogue
  housekeeping`), not part of `prune_on_start`.

Nothing here reads or writes artifacts, the store, the catalogue or the step cache.
"""

from __future__ import annotations

import os
import sqlite3
import stat
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

# Defaults of `capvector catalogue housekeeping` and of prune_on_start (the README quotes them).
KEEP_LOG_DAYS = 30.0
KEEP_LOG_FILES = 200
KEEP_LOG_BYTES = 200 * 1024 * 1024
KEEP_RUN_DAYS = 30.0
KEEP_RUNS = 500
# A log written to within this many seconds belongs to a run still going: never deleted.
ACTIVE_S = 600.0
# The flows this project defines (study, evaluation_flows; `pipeline` and `sweep`, `capvector run`'s and
# `capvector sweep`'s flows until they became studies): the only ones pruned.
CAPVECTOR_FLOWS = ("pipeline", "study", "sweep", "evaluate", "reevaluate")
# How long to wait for the server's background deletion of the pruned runs' logs.
LOG_DELETION_WAIT_S = 20.0

# capvector.tasks.runtime.progress.LOG_FILE_ENV (not imported: this stays cheap)
_LOG_FILE_ENV = "CAPVECTOR_LOG_FILE"


def logs_dir(home: str) -> Path:
    """`<home>/logs` for a local home, `<local cache>/logs` for a remote one (where capvector.flows.cli.main
    writes)."""
    if "://" not in str(home):  # a plain path: local (no fsspec import for prune_on_start)
        return Path(home) / "logs"
    from capvector.artifacts.home import is_local, local_cache_dir

    return (Path(home) if is_local(home) else local_cache_dir(home)) / "logs"


@dataclass
class LogFile:
    path: Path
    size: int
    mtime: float


@dataclass
class LogPrune:
    """What `prune_logs` found and did (with `dry_run`: would do)."""

    folder: str
    deleted: list[LogFile] = field(default_factory=list)
    kept: int = 0
    kept_bytes: int = 0
    dry_run: bool = False

    @property
    def deleted_bytes(self) -> int:
        return sum(f.size for f in self.deleted)

    def as_dict(self) -> dict[str, Any]:
        return {
            "folder": self.folder,
            "dry_run": self.dry_run,
            "deleted": [str(f.path) for f in self.deleted],
            "deleted_bytes": self.deleted_bytes,
            "kept": self.kept,
            "kept_bytes": self.kept_bytes,
        }


def _log_files(folder: Path) -> list[LogFile]:
    """Regular `*.log` files directly in `folder` (lstat: a link is not a log and is never followed),
    newest first."""
    found = []
    try:
        entries = list(os.scandir(folder))
    except FileNotFoundError:
        return []
    for entry in entries:
        if not entry.name.endswith(".log"):
            continue
        try:
            info = entry.stat(follow_symlinks=False)
        except FileNotFoundError:  # removed meanwhile (another prune)
            continue
        if stat.S_ISREG(info.st_mode):
            found.append(LogFile(Path(entry.path), info.st_size, info.st_mtime))
    return sorted(found, key=lambda f: (f.mtime, f.path.name), reverse=True)


def prune_logs(
    home: str,
    keep_days: float | None = KEEP_LOG_DAYS,
    keep_files: int | None = KEEP_LOG_FILES,
    keep_bytes: int | None = KEEP_LOG_BYTES,
    dry_run: bool = False,
    now: float | None = None,
) -> LogPrune:
    """Delete the home's oldest run logs until every limit holds: none older than `keep_days`, at most
    `keep_files` of them, at most `keep_bytes` together (None: no such limit). Oldest first, by
    modification time; the current run's log and logs written to in the last ACTIVE_S seconds are kept
    whatever the limits. Only `*.log` files in `logs_dir(home)` are ever listed or deleted."""
    folder = logs_dir(home)
    now = time.time() if now is None else now
    current = os.environ.get(_LOG_FILE_ENV)
    report = LogPrune(folder=str(folder), dry_run=dry_run)
    kept_files = 0
    full = False  # a limit was reached: every older log goes (oldest first, never a hole in the middle)
    for log in _log_files(folder):  # newest first
        age = now - log.mtime
        active = age < ACTIVE_S or (current is not None and str(log.path) == current)
        full = full or not (
            (keep_days is None or age <= keep_days * 86400)
            and (keep_files is None or kept_files < keep_files)
            and (keep_bytes is None or report.kept_bytes + log.size <= keep_bytes)
        )
        if active or not full:
            kept_files += 1
            report.kept_bytes += log.size
            continue
        if not dry_run:
            try:
                log.path.unlink()
            except FileNotFoundError:
                continue
        report.deleted.append(log)
    report.kept = kept_files
    report.deleted.sort(key=lambda f: f.mtime)
    return report


def prune_on_start(home: str) -> LogPrune | None:
    """Keep a home's run logs bounded with the default limits (KEEP_LOG_FILES files, KEEP_LOG_DAYS days,
    KEEP_LOG_BYTES bytes); for a flow command to call as it starts. One directory listing (about a
    millisecond for a few hundred logs); never raises (returns None when the folder cannot be pruned:
    housekeeping must not stop a run). Prefect's database is not pruned here (that needs a server:
    `capvector catalogue housekeeping`)."""
    try:
        return prune_logs(home)
    except Exception:  # a read-only home, a vanished folder, a remote home's cache not made yet
        return None


# ---------------------------------------------------------------------------------------------- Prefect


@dataclass
class PrefectPrune:
    """What `prune_prefect_db` found and did (with `dry_run`: would do)."""

    server: str  # "embedded (<database>)" or the PREFECT_API_URL
    deleted: list[dict[str, Any]] = field(default_factory=list)  # id, name, flow, state, end_time
    kept: int = 0
    artifacts_deleted: int = 0
    logs_pending: int = 0  # logs the server had not deleted yet when we stopped waiting
    database: str | None = None  # the local SQLite file, when the embedded server was used
    bytes_before: int | None = None
    bytes_after: int | None = None
    vacuum: str = "not asked"
    dry_run: bool = False

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def embedded_database() -> Path | None:
    """The SQLite file of Prefect's embedded server under the current settings (None: not SQLite)."""
    from prefect.settings import get_current_settings

    url = get_current_settings().server.database.connection_url
    url = url.get_secret_value() if hasattr(url, "get_secret_value") else str(url or "")
    prefix = next((p for p in ("sqlite+aiosqlite:///", "sqlite:///") if url.startswith(p)), None)
    if prefix is None or ":memory:" in url:
        return None
    return Path(url[len(prefix) :].split("?", 1)[0]).expanduser()


def _database_bytes(db: Path) -> int:
    return sum(p.stat().st_size for p in (db, Path(f"{db}-wal"), Path(f"{db}-shm")) if p.exists())


def _finished_runs(client: Any) -> list[Any]:
    """Finished (terminal) top-level runs of capvector's flows, newest end first."""
    from prefect.client.schemas.filters import (
        FlowFilter,
        FlowFilterName,
        FlowRunFilter,
        FlowRunFilterParentTaskRunId,
        FlowRunFilterState,
        FlowRunFilterStateType,
    )
    from prefect.client.schemas.objects import TERMINAL_STATES
    from prefect.client.schemas.sorting import FlowRunSort

    runs: list[Any] = []
    page = 200
    while True:
        batch = client.read_flow_runs(
            flow_filter=FlowFilter(name=FlowFilterName(any_=list(CAPVECTOR_FLOWS))),
            flow_run_filter=FlowRunFilter(
                state=FlowRunFilterState(type=FlowRunFilterStateType(any_=list(TERMINAL_STATES))),
                parent_task_run_id=FlowRunFilterParentTaskRunId(is_null_=True),
            ),
            sort=FlowRunSort.END_TIME_DESC,
            limit=page,
            offset=len(runs),
        )
        runs.extend(batch)
        if len(batch) < page:
            break
    return runs


def _ended(run: Any) -> datetime:
    when = run.end_time or run.expected_start_time or run.created
    return when if when.tzinfo else when.replace(tzinfo=UTC)


def _delete_artifacts(client: Any, run_id: Any) -> int:
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterFlowRunId

    count = 0
    while True:
        batch = client.read_artifacts(
            artifact_filter=ArtifactFilter(flow_run_id=ArtifactFilterFlowRunId(any_=[run_id])), limit=200
        )
        for artifact in batch:
            client.delete_artifact(artifact.id)
        count += len(batch)
        if len(batch) < 200:
            return count


def _logs_left(client: Any, run_ids: list[Any]) -> int:
    from prefect.client.schemas.filters import LogFilter, LogFilterFlowRunId

    left = 0
    for i in range(0, len(run_ids), 50):
        chunk = run_ids[i : i + 50]
        left += len(client.read_logs(log_filter=LogFilter(flow_run_id=LogFilterFlowRunId(any_=chunk))))
    return left


def prune_prefect_db(
    older_than_days: float | None = KEEP_RUN_DAYS,
    keep_runs: int | None = KEEP_RUNS,
    dry_run: bool = False,
    vacuum: bool = True,
    now: datetime | None = None,
) -> PrefectPrune:
    """Delete finished flow runs of capvector's flows that ended more than `older_than_days` ago or
    are not among the `keep_runs` newest (None: no such limit), through Prefect's client, with their
    task runs, states, logs and UI artifacts; then VACUUM the embedded SQLite database (`vacuum`).

    The server is PREFECT_API_URL's, else Prefect's embedded one on $PREFECT_HOME's database (started
    for the call and stopped before VACUUM). Runs that are not finished are never deleted, nor runs of
    other flows. `now` (UTC): for tests."""
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_URL

    external = PREFECT_API_URL.value()
    database = None if external else embedded_database()
    report = PrefectPrune(
        server=external or f"embedded ({database or 'not SQLite'})",
        database=str(database) if database else None,
        dry_run=dry_run,
    )
    if database is not None and database.exists():
        report.bytes_before = _database_bytes(database)
    started_here = not external and not _embedded_server_running()
    now = now or datetime.now(UTC)
    cutoff = None if older_than_days is None else now - timedelta(days=older_than_days)
    try:
        with get_client(sync_client=True) as client:
            runs = _finished_runs(client)
            doomed = [
                run
                for i, run in enumerate(runs)
                if (keep_runs is not None and i >= keep_runs) or (cutoff is not None and _ended(run) < cutoff)
            ]
            report.kept = len(runs) - len(doomed)
            flows = {}
            for run in sorted(doomed, key=_ended):
                if run.flow_id not in flows:
                    flows[run.flow_id] = client.read_flow(run.flow_id).name
                report.deleted.append(
                    {
                        "id": str(run.id),
                        "name": run.name,
                        "flow": flows[run.flow_id],
                        "state": run.state_type.value if run.state_type else None,
                        "end_time": _ended(run).isoformat(),
                    }
                )
                if not dry_run:
                    report.artifacts_deleted += _delete_artifacts(client, run.id)
                    client.delete_flow_run(run.id)
            if doomed and not dry_run:  # the server deletes their logs in the background: let it finish
                ids = [run.id for run in doomed]
                deadline = time.monotonic() + LOG_DELETION_WAIT_S
                while (left := _logs_left(client, ids)) and time.monotonic() < deadline:
                    time.sleep(0.2)
                report.logs_pending = left
    finally:
        if started_here:  # a server this process had before (its flows') is left to Prefect's exit
            _stop_embedded_server()
    if database is None:
        report.vacuum = "not run: the runs live on the server at PREFECT_API_URL, whose database is its own"
    elif dry_run or not vacuum:
        report.vacuum = "not asked"
    elif database.exists():
        report.vacuum = _vacuum(database)
        report.bytes_after = _database_bytes(database)
    return report


def _embedded_server_running() -> bool:
    """Whether Prefect's client already runs its embedded server in this process (one per process)."""
    from prefect.server.api.server import SubprocessASGIServer

    return SubprocessASGIServer().running


def _stop_embedded_server() -> None:
    """Stop the embedded server Prefect's client started for this call (it holds the database open)."""
    from prefect.server.api.server import SubprocessASGIServer

    SubprocessASGIServer().stop()


def _vacuum(database: Path) -> str:
    """VACUUM the SQLite file and truncate its write-ahead log; a run using it meanwhile makes it wait,
    then give up (a busy database is left as it is: pruning is done, only the file keeps its size)."""
    try:
        con = sqlite3.connect(database, timeout=10)
        try:
            con.execute("VACUUM")
            con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        finally:
            con.close()
    except sqlite3.OperationalError as exc:
        return f"skipped: {exc} (another run is using the database; prune again when it is done)"
    return "done"
