"""`capvector verify [ID…|--all]`: check the store against its ids, its seals and the catalogue.

For each artifact: its sidecar must pass its seal (metadata not edited since registration), every
byte must hash to the recorded sha256 (read from the store itself: no memo, no cache, nothing
written), a directory must hold no file beyond its record, and its kind, name and parent edges must
agree with the catalogue's row, written at registration (which catches a sidecar edited and re-sealed
by someone who did not also edit the catalogue). Exit 1 naming each bad id; 0 on a clean store.

With `--all`, the step cache's index (content key -> artifact id) is checked too: an entry naming an
artifact recorded under another cache key (swapped or edited entries) is listed as
`MISMATCH step-cache/<key>` and fails the check; a run treats such an entry as a miss
(capvector.tasks.runtime.caching). So is the store's own index (`index/<key[:2]>/<key>.json`, a remote
home's entries, listed once; capvector.tasks.runtime.index_verify): each object must be an entry within
its size limit naming an artifact of the store that is its key's result, with its companions intact; a
bad one is listed as `CORRUPT|MISSING|MISMATCH index/<key>` and fails the check. The named artifacts are
not hashed again (their verdicts above are reused); nothing is removed or rewritten.
"""

from __future__ import annotations

import json
import sys
import time
from typing import Annotated, Any

import typer

from capvector.artifacts.records import IntegrityVerdict
from capvector.flows.runtime.home import resolve_home


def verify(
    ids: Annotated[list[str] | None, typer.Argument(help="artifact ids or unique prefixes")] = None,
    all_: Annotated[bool, typer.Option("--all", help="every artifact in the store")] = False,
    strict: Annotated[
        bool, typer.Option("--strict", help="fail on unsealed sidecars (written before sealing) too")
    ] = False,
    home: Annotated[str | None, typer.Option("--home", help="capvector home")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="print every verdict as JSON")] = False,
) -> None:
    """Re-hash artifacts against their ids and check their sealed metadata; exit 1 naming each bad id."""
    from capvector.artifacts.api import ArtifactsAPI

    if bool(ids) == all_:
        raise typer.BadParameter("give artifact ids or --all (not both)")
    # catch_up=False: a check reports, it does not index on open (which could index a forgery before
    # the comparison with the catalogue below sees it).
    api = ArtifactsAPI(resolve_home(home), catch_up=False)
    targets = sorted(api.store.iter_ids()) if all_ else list(ids or [])
    indexed = _catalogue_lineage(api)
    progress = _Progress(len(targets), enabled=all_)
    verdicts = []
    for target in targets:
        verdict = api.store.audit(target)
        if indexed is not None and verdict.status in ("ok", "unsealed"):
            verdict = _compare_with_catalogue(api, verdict, indexed)
        verdicts.append(verdict)
        progress.step(verdict)
    progress.close()
    cache_verdicts = _cache_verdicts(api, resolve_home(home)) if all_ else []
    index_count, index_verdicts = _index_verdicts(api, verdicts) if all_ else (0, [])

    failed = [v for v in verdicts if v.bad or (strict and v.status == "unsealed")]
    if as_json:
        typer.echo(json.dumps([v.model_dump() for v in verdicts + cache_verdicts + index_verdicts], indent=1))
    else:
        for v in verdicts:
            if v.status != "ok":
                typer.echo(f"{v.status.upper():<9} {v.id}  {v.detail}")
        counts = {s: sum(v.status == s for v in verdicts) for s in ("ok", "unsealed")}
        bad = sum(v.bad for v in verdicts)
        typer.echo(
            f"{len(verdicts)} artifacts, {_size(progress.bytes)} hashed in {progress.elapsed():.1f} s: "
            f"{counts['ok']} ok, {counts['unsealed']} unsealed, {bad} bad"
        )
        for v in cache_verdicts:
            typer.echo(f"{v.status.upper():<9} {v.id}  {v.detail}")
        if cache_verdicts:
            typer.echo(f"{len(cache_verdicts)} step-cache entries name an artifact of another key")
        for v in index_verdicts:
            typer.echo(f"{v.status.upper():<9} {v.id}  {v.detail}")
        if index_count or index_verdicts:
            typer.echo(f"{index_count} index objects in the store: {len(index_verdicts)} bad")
        if indexed is None:
            typer.echo("the catalogue could not be read: lineage was not compared with it", err=True)
    if failed or cache_verdicts or index_verdicts:
        raise typer.Exit(1)


def _cache_verdicts(api: Any, home: str) -> list[IntegrityVerdict]:
    """One `mismatch` verdict (id `step-cache/<key>`) per index entry that is not its key's result."""
    from capvector.tasks.runtime.caching import index_problems

    return [
        IntegrityVerdict(
            id=f"step-cache/{key}",
            status="mismatch",
            detail=f"{problem}: the next run recomputes this step (remove the entry to silence this)",
        )
        for key, problem in index_problems(home, api)
    ]


def _index_verdicts(api: Any, verdicts: list[IntegrityVerdict]) -> tuple[int, list[IntegrityVerdict]]:
    """(index objects in the store, a verdict per bad one); the artifacts' verdicts say which are whole."""
    from capvector.tasks.runtime.index_verify import store_index_verdicts

    return store_index_verdicts(api.store, {v.id: not v.bad for v in verdicts})


def _catalogue_lineage(api: Any) -> dict[str, tuple[str, str, set[tuple[str, str]]]] | None:
    """{id: (kind, name, {(parent, role)})} as the catalogue recorded them; None when unreadable."""
    try:
        _, rows = api.query_rows("SELECT id, kind, name FROM artifacts")
        _, edges = api.query_rows("SELECT child, parent, role FROM edges")
    except Exception as e:  # a missing, locked or newer catalogue: check the store alone
        typer.echo(f"catalogue: {e}", err=True)
        return None
    out = {str(i): (str(k), str(n), set()) for i, k, n in rows}
    for child, parent, role in edges:
        if child in out:
            out[child][2].add((str(parent), str(role)))
    return out


def _compare_with_catalogue(
    api: Any, verdict: IntegrityVerdict, indexed: dict[str, tuple[str, str, set[tuple[str, str]]]]
) -> IntegrityVerdict:
    if verdict.id not in indexed:
        return verdict  # registered but not indexed yet (a writer died before its row): nothing to compare
    record = api.store.get(verdict.id)
    kind, name, parents = indexed[verdict.id]
    differs = []
    if record.kind != kind:
        differs.append(f"kind {record.kind!r} (catalogue: {kind!r})")
    if record.name != name:
        differs.append(f"name {record.name!r} (catalogue: {name!r})")
    sidecar_parents = {(p.id, p.role) for p in record.parents}
    if sidecar_parents != parents:
        extra = ", ".join(f"{r}={i[:12]}" for i, r in sorted(sidecar_parents - parents)) or "-"
        lacking = ", ".join(f"{r}={i[:12]}" for i, r in sorted(parents - sidecar_parents)) or "-"
        differs.append(f"parents the catalogue lacks: {extra}; catalogue parents it lacks: {lacking}")
    if not differs:
        return verdict
    detail = (
        "sidecar and catalogue disagree: "
        + "; ".join(differs)
        + " (an edit re-sealed by hand, or a deliberate re-registration a catalogue rebuild has not seen)"
    )
    return verdict.model_copy(update={"status": "mismatch", "detail": detail})


class _Progress:
    """One line on stderr: rewritten in place on a terminal, else printed every few seconds."""

    def __init__(self, total: int, enabled: bool):
        self.total, self.enabled, self.done, self.bytes, self.bad = total, enabled, 0, 0, 0
        self.tty = sys.stderr.isatty()
        self.start = self.last = time.monotonic()

    def elapsed(self) -> float:
        return time.monotonic() - self.start

    def step(self, verdict: IntegrityVerdict) -> None:
        self.done += 1
        self.bytes += verdict.size
        self.bad += verdict.bad
        now = time.monotonic()
        if not self.enabled or now - self.last < (0.2 if self.tty else 5.0):
            return
        self.last = now
        self._print()

    def _print(self) -> None:
        rate = self.bytes / max(self.elapsed(), 1e-9)
        line = f"verified {self.done}/{self.total}  {_size(self.bytes)}  {_size(rate)}/s  {self.bad} bad"
        if self.tty:
            sys.stderr.write("\r" + line + "\033[K")
            sys.stderr.flush()
        else:
            typer.echo(line, err=True)

    def close(self) -> None:
        if self.enabled and self.tty:
            self._print()
            sys.stderr.write("\n")


def _size(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1000:
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} TB"
