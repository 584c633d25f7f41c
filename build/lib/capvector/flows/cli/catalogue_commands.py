"""`capvector catalogue sync|rebuild|verify|gc`: keep the DuckDB catalogue in step with the store;
`capvector catalogue housekeeping`: keep run logs and Prefect's run history bounded
(capvector.flows.runtime.housekeeping).

The store is the truth and the catalogue an index of it. Every command opens the catalogue without the
automatic catch-up (capvector.artifacts.api), so `verify` reports what an open would have repaired. `gc`
removes what the store itself left over; `housekeeping` never looks at the store or the catalogue.
"""

from __future__ import annotations

import json
from typing import Annotated, Any

import typer

from capvector.flows.cli.common import HomeOption
from capvector.flows.runtime.home import resolve_home
from capvector.flows.runtime.housekeeping import (
    KEEP_LOG_BYTES,
    KEEP_LOG_DAYS,
    KEEP_LOG_FILES,
    KEEP_RUN_DAYS,
    KEEP_RUNS,
)

catalogue_app = typer.Typer(
    no_args_is_help=True,
    help="Keep the catalogue (an index, rebuildable) in step with the artifact store (the truth); "
    "`housekeeping` bounds run logs and Prefect's run history.",
)

JsonOption = Annotated[bool, typer.Option("--json", help="print machine-readable JSON")]


def _api(home: str | None):
    from capvector.artifacts.api import ArtifactsAPI

    return ArtifactsAPI(resolve_home(home), catch_up=False)


def _echo_json(data: Any) -> None:
    typer.echo(json.dumps(data, indent=1, default=str))


def _listed(title: str, ids: list[str]) -> list[str]:
    return [f"{title}: {len(ids)}", *(f"  {i}" for i in ids)] if ids else []


def _index_report(report, done: str, skipped: str, as_json: bool) -> None:
    """sync and rebuild print the same report; verification failures make the command fail."""
    if as_json:
        _echo_json(report.model_dump())
    else:
        typer.echo(f"{done}: {report.artifacts} artifacts, {report.runs} runs in {report.seconds:.2f} s")
        for line in _listed(skipped, report.corrupt):
            typer.echo(line)
        kept = getattr(report, "kept", [])
        for line in _listed("catalogue rows kept over an unsealed or failing sidecar", kept):
            typer.echo(line)
        fresh = sorted(set(getattr(report, "unsealed", [])) - set(kept))
        for line in _listed("indexed from unsealed sidecars (metadata not protected by a seal)", fresh):
            typer.echo(line)
    if report.corrupt:
        raise typer.Exit(1)


@catalogue_app.command()
def sync(home: HomeOption = None, as_json: JsonOption = False) -> None:
    """Index what the store has and the catalogue lacks (reads only the missing sidecars)."""
    _index_report(_api(home).sync(), "indexed", "not indexed, failed verification", as_json)


@catalogue_app.command()
def rebuild(home: HomeOption = None, as_json: JsonOption = False) -> None:
    """Recreate the catalogue from the store alone (one transaction: readers see old or new)."""
    _index_report(_api(home).rebuild(), "rebuilt", "skipped, failed verification", as_json)


@catalogue_app.command()
def verify(home: HomeOption = None, as_json: JsonOption = False) -> None:
    """Report catalogue rows without objects and objects without rows; exit 1 on any difference."""
    report = _api(home).verify()
    if as_json:
        _echo_json({**report.model_dump(), "ok": report.ok})
    else:
        typer.echo(f"store: {report.objects} artifacts; catalogue: {report.rows} rows")
        for title, ids in [
            (
                "catalogue rows without an object in the store (`capvector catalogue gc` removes them)",
                report.rows_without_objects,
            ),
            (
                "artifacts in the store without a catalogue row (`capvector catalogue sync` indexes them)",
                report.objects_without_rows,
            ),
            ("run records without a catalogue row", report.runs_without_rows),
            ("run rows without a run record in the store", report.rows_without_runs),
        ]:
            for line in _listed(title, ids):
                typer.echo(line)
        typer.echo("in step" if report.ok else "differences found")
    if not report.ok:
        raise typer.Exit(1)


@catalogue_app.command()
def gc(
    older_than: Annotated[
        float, typer.Option("--older-than", help="seconds: younger leftovers may be a write in progress")
    ] = 3600.0,
    home: HomeOption = None,
    as_json: JsonOption = False,
) -> None:
    """Remove store leftovers (staging) and rows of artifacts no longer stored; quarantine objects
    without a sidecar (never deleted; left in place when something names them as a parent).

    Also the rows of run records no longer in the store and snapshot folders of killed readers.

    Old run logs and Prefect flow runs: `capvector catalogue housekeeping`."""
    report = _api(home).gc(older_than)
    if as_json:
        _echo_json(report.model_dump())
        return
    for title, items in [
        ("store leftovers removed", report.store),
        ("objects without a sidecar moved to quarantine (not deleted)", report.quarantined),
        ("objects without a sidecar kept in place (named as a parent)", report.kept),
        ("catalogue rows removed (artifact no longer in the store)", report.rows),
        ("run rows removed", report.runs),
        ("reader snapshots removed", report.snapshots),
    ]:
        typer.echo(f"{title}: {len(items)}")
        for item in items:
            typer.echo(f"  {item}")


HOUSEKEEPING_HELP = (
    "Delete old run logs and old Prefect flow runs; artifacts, the store, the catalogue and the step "
    "cache are never touched."
    "\n\n"
    "Logs: `*.log` files in <home>/logs (a remote home: its local cache folder), oldest first, until none "
    "is older than --logs-older-than and at most --keep-logs files and --keep-log-mb remain; a log written "
    "to in the last 10 minutes (a run still going) is always kept."
    "\n\n"
    "Runs: finished runs of capvector's flows (pipeline, study, sweep, evaluate, reevaluate) that ended "
    "more than --runs-older-than days ago or are beyond the --keep-runs newest, with their task runs, "
    "logs and UI artifacts, are deleted through Prefect's client: on the server at PREFECT_API_URL, else "
    "on the embedded database in $PREFECT_HOME (a server is started for the call, ~10 s), which is then "
    "VACUUMed. Prefect deletes events itself: its server removes those older than "
    "PREFECT_SERVER_EVENTS_RETENTION_PERIOD (7 days) whenever it starts."
)


@catalogue_app.command(help=HOUSEKEEPING_HELP)
def housekeeping(
    logs_older_than: Annotated[
        float, typer.Option("--logs-older-than", help="days: run logs older than this are deleted")
    ] = KEEP_LOG_DAYS,
    keep_logs: Annotated[int, typer.Option("--keep-logs", help="run logs kept at most (the newest)")] = (
        KEEP_LOG_FILES
    ),
    keep_log_mb: Annotated[
        float, typer.Option("--keep-log-mb", help="MB of run logs kept at most (the newest)")
    ] = KEEP_LOG_BYTES / 2**20,
    runs_older_than: Annotated[
        float,
        typer.Option(
            "--runs-older-than", help="days: finished Prefect flow runs that ended before are deleted"
        ),
    ] = KEEP_RUN_DAYS,
    keep_runs: Annotated[
        int, typer.Option("--keep-runs", help="finished Prefect flow runs kept at most (the newest)")
    ] = KEEP_RUNS,
    logs: Annotated[bool, typer.Option("--logs/--no-logs", help="prune the home's run logs")] = True,
    runs: Annotated[bool, typer.Option("--runs/--no-runs", help="prune Prefect's flow runs")] = True,
    vacuum: Annotated[
        bool, typer.Option("--vacuum/--no-vacuum", help="VACUUM the embedded Prefect database afterwards")
    ] = True,
    dry_run: Annotated[
        bool, typer.Option("--dry-run", help="list what would be deleted; delete nothing")
    ] = False,
    home: HomeOption = None,
    as_json: JsonOption = False,
) -> None:
    """Prune run logs (capvector.flows.runtime.housekeeping.prune_logs) and Prefect flow runs
    (prune_prefect_db)."""
    from capvector.flows.runtime.housekeeping import prune_logs, prune_prefect_db

    found: dict[str, Any] = {}
    if logs:
        found["logs"] = prune_logs(
            resolve_home(home),
            keep_days=logs_older_than,
            keep_files=keep_logs,
            keep_bytes=int(keep_log_mb * 2**20),
            dry_run=dry_run,
        ).as_dict()
    if runs:
        found["runs"] = prune_prefect_db(
            older_than_days=runs_older_than, keep_runs=keep_runs, dry_run=dry_run, vacuum=vacuum
        ).as_dict()
    if as_json:
        _echo_json(found)
        return
    verb = "would delete" if dry_run else "deleted"
    if "logs" in found:
        report = found["logs"]
        typer.echo(
            f"run logs in {report['folder']}: {verb} {len(report['deleted'])} "
            f"({_mb(report['deleted_bytes'])}), kept {report['kept']} ({_mb(report['kept_bytes'])})"
        )
        for path in report["deleted"]:
            typer.echo(f"  {path}")
    if "runs" in found:
        report = found["runs"]
        typer.echo(
            f"Prefect flow runs on {report['server']}: {verb} {len(report['deleted'])}, kept {report['kept']}"
        )
        for run in report["deleted"]:
            typer.echo(f"  {run['end_time'][:19]}  {run['flow']:<10}  {run['state']:<9}  {run['name']}")
        if report["logs_pending"]:
            typer.echo(f"  {report['logs_pending']} of their log lines are still being deleted by the server")
        if report["bytes_after"] is not None:
            typer.echo(
                f"database {report['database']}: {_mb(report['bytes_before'])} -> "
                f"{_mb(report['bytes_after'])} (VACUUM {report['vacuum']})"
            )
        elif not dry_run:
            typer.echo(f"VACUUM {report['vacuum']}")


def _mb(n: int | None) -> str:
    return "?" if n is None else f"{n / 2**20:.1f} MB"
