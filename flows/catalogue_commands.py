"""`capvector catalogue sync|rebuild|verify|gc`: keep the DuckDB catalogue in step with the store.

The store is the truth and the catalogue an index of it. Every command opens the catalogue without the
automatic catch-up (artifacts.api), so `verify` reports what an open would have repaired.
"""

from __future__ import annotations

import json
from typing import Annotated, Any

import typer

from flows.home import resolve_home

catalogue_app = typer.Typer(
    no_args_is_help=True,
    help="Keep the catalogue (an index, rebuildable) in step with the artifact store (the truth).",
)

HomeOption = Annotated[str | None, typer.Option("--home", help="capvector home (default: $CAPVECTOR_HOME)")]
JsonOption = Annotated[bool, typer.Option("--json", help="print machine-readable JSON")]


def _api(home: str | None):
    from artifacts.api import ArtifactsAPI

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

    Also the rows of run records no longer in the store and snapshot folders of killed readers."""
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
