"""The read-only commands (artifacts, lineage, scores, compare, report, studies, sql), `import` and
`import-dataset`: what a researcher asks of the catalogue, and what they bring to it. None of the
read-only ones imports torch, pandas, Prefect or Meta-World to answer."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from capvector.flows.cli.common import (
    HomeOption,
    JsonOption,
    Table,
    console,
    err,
    print_json,
    text_table,
    workspace,
)
from capvector.flows.views.lineage import as_tree, edge_notes, keep_kinds, mermaid_lineage

artifacts_app = typer.Typer(no_args_is_help=True, help="List, show and get artifacts.")


@artifacts_app.command("list")
def artifacts_list(
    kind: Annotated[str | None, typer.Option(help="only this kind")] = None,
    limit: int = 50,
    home: HomeOption = None,
    as_json: JsonOption = False,
) -> None:
    """Artifacts in the catalogue, newest first."""
    ws = workspace(home)
    sql = "SELECT id, kind, name, size_bytes, created_at FROM artifacts"
    params: list[Any] = []
    if kind:
        sql += " WHERE kind = ?"
        params.append(kind)
    columns, rows = ws.api.query_rows(sql + f" ORDER BY created_at DESC LIMIT {int(limit)}", params)
    if as_json:
        print_json([dict(zip(columns, r, strict=True)) for r in rows])
        return
    table = Table("id", "kind", "name", "size", "created")
    for aid, kind_, name, size, created in rows:
        table.add_row(aid[:12], kind_, name, f"{size:,}", str(created)[:19])
    console.print(table)


@artifacts_app.command("show")
def artifacts_show(artifact_id: str, home: HomeOption = None, as_json: JsonOption = False) -> None:
    """The full record of one artifact (its sidecar: config, parents, versions, runs), as JSON with or
    without `--json` (taken, as every read command takes it, so a script can pass it everywhere)."""
    print_json(workspace(home).api.get(artifact_id).model_dump(mode="json"))


@artifacts_app.command("get")
def artifacts_get(
    artifact_id: str,
    out: Annotated[Path, typer.Option("-o", "--out", help="a new path, or a folder for a file")],
    home: HomeOption = None,
) -> None:
    """Copy an artifact out of the store (verified against its id first): a file artifact to OUT, or into
    OUT/<its file name> when OUT is an existing folder; a folder artifact to the new folder OUT. Prints
    the path written."""
    import shutil

    from capvector.artifacts.store import copy_in

    ws = workspace(home)
    record = ws.api.get(artifact_id)
    source = ws.api.path(record.id)  # re-hashed: changed bytes are an error naming the id
    target = out / source.name if record.layout == "file" and out.is_dir() else out
    if target.exists():
        raise FileExistsError(f"{target} exists: artifacts get writes only to a new path")
    target.parent.mkdir(parents=True, exist_ok=True)
    staged = target.with_name(f".{target.name}.partial")

    def discard() -> None:
        shutil.rmtree(staged) if staged.is_dir() else staged.unlink(missing_ok=True)

    discard()  # left by an interrupted get
    try:
        copy_in(source, staged)  # the store's copy: reflinks where the filesystem has them
        staged.rename(target)
    finally:
        discard()
    print(target)


def _json_format(fmt: str, as_json: bool, default: str) -> str:
    """`--format json` when `--json` is given (with no other format asked for)."""
    if not as_json:
        return fmt
    if fmt not in (default, "json"):
        raise typer.BadParameter(f"--json prints JSON: give it or --format {fmt}, not both")
    return "json"


def lineage(
    artifact_id: str,
    descendants: Annotated[bool, typer.Option("--descendants", help="what descends from it")] = False,
    fmt: Annotated[str, typer.Option("--format", help="tree | json | mermaid")] = "tree",
    depth: Annotated[int | None, typer.Option(help="maximum depth")] = None,
    kinds: Annotated[
        str | None, typer.Option("--kinds", help="only these kinds, e.g. checkpoint,vector (contracted)")
    ] = None,
    hide: Annotated[str | None, typer.Option("--hide", help="leave out these kinds (contracted)")] = None,
    home: HomeOption = None,
    as_json: JsonOption = False,
) -> None:
    """Ancestors (default) or descendants of an artifact, with the role of every edge.

    `--kinds`/`--hide` keep some kinds only; a path through the others becomes one edge (its roles
    joined by →), so what is kept stays connected, and `--depth` counts the kept hops. `--json` is
    `--format json`. A Mermaid graph over Mermaid's edge limit is drawn contracted, with a note on
    stderr saying what was grouped."""
    fmt = _json_format(fmt, as_json, "tree")
    ws = workspace(home)
    record = ws.api.get(artifact_id)
    filtered = kinds is not None or hide is not None
    rows = (ws.api.descendants if descendants else ws.api.ancestors)(record.id, None if filtered else depth)
    if filtered:
        kept, hidden = ({k.strip() for k in v.split(",") if k.strip()} if v else None for v in (kinds, hide))
        rows = keep_kinds(rows, record, not descendants, kept, hidden, depth)
    notes = {} if fmt == "json" else edge_notes(ws.api, [record.id, *(r.id for r in rows)])
    if fmt == "json":
        print_json([r.model_dump() for r in rows])
    elif fmt == "mermaid":
        graph, note = mermaid_lineage(rows, record, ancestors=not descendants, notes=notes)
        typer.echo(graph)
        if note:
            typer.echo(note, err=True)  # stdout stays one graph, to paste whole
    elif fmt == "tree":
        typer.echo(as_tree(rows, record, notes))
    else:
        raise typer.BadParameter(f"unknown format {fmt!r}; use tree, json or mermaid")


def scores(
    artifact_id: str,
    fingerprint: Annotated[
        str | None,
        typer.Option(
            help="the evaluation protocol: test, validation, or a fingerprint (a unique prefix of 6+ "
            "characters, e.g. the 12 in the table)"
        ),
    ] = None,
    home: HomeOption = None,
    as_json: JsonOption = False,
) -> None:
    """Per-task scores of the artifact and everything descended from it, under one protocol."""
    from capvector.artifacts.errors import MixedFingerprints
    from capvector.flows.evaluation.protocols import SHOWN, listing, protocols, resolve

    api = workspace(home).api
    try:
        rows = api.scores(artifact_id, None)
    except MixedFingerprints as e:
        choices = protocols(api, e.fingerprints)
        if fingerprint is None:
            raise ValueError(
                f"the scores of {artifact_id} come from {len(choices)} evaluation protocols, never shown "
                f"together: {listing(choices)}; choose one with --fingerprint test, validation or a "
                "fingerprint prefix"
            ) from None
        rows = api.scores(artifact_id, resolve(fingerprint, choices, artifact_id))
    else:
        if fingerprint is not None:  # one protocol (or none) here: the choice must still name it
            resolve(fingerprint, protocols(api, {r.fingerprint for r in rows}), artifact_id)
    shown = protocols(api, {r.fingerprint for r in rows})  # one (or none): never mixed
    if as_json:
        names = {p.fingerprint: p.name for p in shown}
        print_json([{**r.model_dump(mode="json"), "protocol": names[r.fingerprint]} for r in rows])
        return
    table = Table("checkpoint", "name", "depth", "task", "success", "episodes", "protocol", "evaluated")
    widest_task = max([4, *(len(r.task) for r in rows)])
    for i, width in ((0, 12), (3, widest_task), (6, SHOWN)):  # ids and task names whole, even in a terminal
        table.columns[i].no_wrap, table.columns[i].min_width = True, width
    for r in rows:
        table.add_row(
            r.checkpoint_id[:12],
            r.checkpoint_name or "",
            str(r.depth),
            r.task,
            f"{100 * r.success_rate:.1f}%",
            str(r.n_episodes),
            r.fingerprint[:SHOWN],
            str(r.evaluated_at)[:19],
        )
    console.print(table)
    for p in shown:
        typer.echo(f"protocol {p.describe()}")


def compare(
    checkpoints: Annotated[list[str], typer.Argument(help="checkpoint ids to compare")],
    fingerprint: Annotated[str | None, typer.Option(help="protocol to compare under")] = None,
    plot: Annotated[Path | None, typer.Option(help="write a PNG bar chart here")] = None,
    home: HomeOption = None,
    as_json: JsonOption = False,
) -> None:
    """Latest per-task scores of several checkpoints under one protocol, side by side."""
    from capvector.flows.views.comparison import compare_checkpoints, plot_compare

    ws = workspace(home)
    result = compare_checkpoints(ws, checkpoints, fingerprint)
    if plot is not None:
        plot_compare(result, plot)
        err.print(f"wrote {plot}")
    if as_json:
        print_json(result.model_dump(mode="json"))
        return
    tasks = sorted({t for row in result.rows for t in row.success_rates})
    table = Table("checkpoint", "name", *tasks, "mean")
    for row in result.rows:
        table.add_row(
            row.checkpoint_id[:12],
            row.name,
            *[f"{100 * row.success_rates[t]:.0f}%" for t in tasks],
            f"{100 * row.mean:.1f}%",
        )
    console.print(table)
    console.print(f"protocol {result.fingerprint[:12]}")


def report(
    report_id: Annotated[
        str | None, typer.Argument(help="a study or report artifact (default: the latest study, else report)")
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option(
            "-o",
            "--out",
            help="Markdown file to write (default: <home>/reports/; a remote home's local cache folder)",
        ),
    ] = None,
    section: Annotated[
        list[str] | None,
        typer.Option(help="'TITLE=REPORT_ID': another report as an extra table (repeatable)"),
    ] = None,
    sweep_id: Annotated[
        list[str] | None, typer.Option("--sweep", help="a sweep artifact to include (repeatable)")
    ] = None,
    notes: Annotated[Path | None, typer.Option(help="a Markdown file of analysis to include")] = None,
    home: HomeOption = None,
    as_json: JsonOption = False,
) -> None:
    """Markdown + PNG figures of a study (curves, paired differences, per task) or a pipeline report;
    `--json` prints what was written (the file, and the study or report it shows) as JSON."""
    from capvector.flows.study.figures import default_report_path, latest_study_id, write_study_report

    ws = workspace(home)
    record = ws.api.get(report_id) if report_id else None
    study_id = record.id if record is not None and record.kind == "study" else None
    if record is None:
        study_id = latest_study_id(ws)
    if study_id is not None:
        path = write_study_report(ws, study_id, out or default_report_path(ws, study_id))
        if as_json:
            print_json({"path": str(path), "kind": "study", "id": study_id})
        else:
            console.print(f"wrote {path} and its figures")
        return
    from capvector.flows.recipe.report import latest_report_id, write_report

    sections = {}
    for item in section or []:
        if "=" not in item:
            raise typer.BadParameter(f"--section {item!r} must look like 'TITLE=REPORT_ID'")
        title, rid = item.rsplit("=", 1)
        sections[title] = rid
    rid = record.id if record is not None else latest_report_id(ws)
    target = out or ws.local_root / "reports" / f"report-{rid[:12]}.md"  # a remote home: its local cache
    text = notes.read_text() if notes else None
    path = write_report(ws, rid, target, sections, sweep_id, text)
    if as_json:
        print_json({"path": str(path), "kind": "report", "id": rid})
    else:
        console.print(f"wrote {path}")


def studies(
    refs: Annotated[
        list[str] | None,
        typer.Argument(help="two studies to compare: artifact ids (a prefix is enough) or study JSON files"),
    ] = None,
    home: HomeOption = None,
    as_json: JsonOption = False,
) -> None:
    """The studies of this home, one row each (stage, design, gate, headline difference); with two, side by
    side: design, preconditions and every comparison at the primary endpoint. A study of another home:
    `capvector --home OTHER artifacts get ID -o study.json`, then pass the file."""
    from capvector.flows.views.studies import compare_studies, list_studies, load_study_doc

    ws = workspace(home)
    if not refs:
        rows = list_studies(ws)
        if as_json:
            print_json([r.model_dump() for r in rows])
            return
        columns = ("id", "name", "stage", "created_at", "code_version", "draws", "seeds", "tasks",
                   "goals_per_task", "gate", "headline")  # fmt: skip
        typer.echo(text_table(columns, [[str(getattr(r, c)) for c in columns] for r in rows]))
        return
    if len(refs) != 2:
        raise typer.BadParameter(f"give two studies to compare, or none to list them (got {len(refs)})")
    (label_a, a), (label_b, b) = (load_study_doc(ws, ref) for ref in refs)
    sections = compare_studies(a, b)
    if as_json:
        print_json({"studies": [label_a, label_b], **{k: [list(r) for r in v] for k, v in sections.items()}})
        return
    for title, rows in sections.items():
        typer.echo(f"\n{title}\n" + text_table(("", label_a[:12], label_b[:12]), rows))


def sql(query: str, home: HomeOption = None, as_json: JsonOption = False) -> None:
    """Read-only SQL over the catalogue (anything but reading is refused)."""
    columns, rows = workspace(home).api.query_rows(query)
    if as_json:
        print_json([dict(zip(columns, r, strict=True)) for r in rows])
    else:
        typer.echo(text_table(columns, rows))


def import_checkpoint(
    path: Path,
    name: Annotated[str | None, typer.Option(help="name in the catalogue")] = None,
    kind: str = "checkpoint",
    home: HomeOption = None,
) -> None:
    """Register an outside safetensors checkpoint (file or sharded directory) in the store."""
    from capvector.tasks.vector_commands import import_path

    record = import_path(workspace(home), path, kind, name)
    console.print(record.id)


def import_dataset(
    directory: Annotated[Path, typer.Argument(help="a LeRobotDataset v3.0 folder (meta/info.json, data/)")],
    name: Annotated[
        str | None, typer.Option(help="name in the catalogue (default: lerobot <folder>)")
    ] = None,
    home: HomeOption = None,
    as_json: JsonOption = False,
) -> None:
    """Register a LeRobotDataset v3.0 folder as a demonstration `dataset` artifact: observation.state,
    action, episodes and task texts (and one image feature, and capvector's own features) read into
    capvector's format. Its config names the folder and its content hash; a folder `capvector export
    --format lerobot` wrote reads back exactly, with the exported artifact as its `source` parent.
    Prints the new artifact's id (and notes on what was left out, e.g. video features, on stderr)."""
    from capvector.tasks.lerobot_dataset import import_dataset as register

    record, notes = register(workspace(home), directory, name)
    if as_json:
        print_json({"id": record.id, "name": record.name, "config": record.config, "notes": notes})
        return
    for note in notes:
        err.print(f"note: {note}", markup=False, highlight=False)
    console.print(record.id)
