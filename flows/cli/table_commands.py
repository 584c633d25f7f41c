"""`capvector runs` and `capvector export`: the experiment table and Parquet files, in DuckDB SQL.

A run is a checkpoint the `train` step produced (its record's config holds the step's config under
`train_step`, and a `summary`); the checkpoints it kept along the way (`train.snapshot_steps`) are its
parents with role `snapshot` (edge attribute `budget`) and are not runs of their own. Its columns come
from the catalogue alone:

- study: the study whose flow run trained it (the `study` flow's config name), else every study whose
  analysis has it in its lineage; status: the state of the flow run that recorded it; train_s: its
  training's wall time from its summary (steps trained here / steps per second); code_revision: the
  `git describe` of the checkout that trained it (its record's `code_version`, a catalogue column);
- stage and arm from its name as the flows give it: `downstream <arm> [draw|replicate <d>] seed <s>`
  (downstream), `tune <arm> ...` (tuning, a sweep's cells included), `<arm> α=...` (sweep: the sweep flow's
  cells, before a sweep was a study), `... θ_pt` (pretrain), `... θ_ft` / `... θ_ao` (extraction), anything
  else `other`;
- draw (replicate): `draw <d>` (`replicate <r>`) in its name, else in the name of its `init` or
  `regularized_by` parent (a study's `downstream capvector seed 0` starts from `draw 1 merge θ_meta`);
  none for runs shared by every draw;
- seed, lr, steps, adapter, aux, aux_weight and λ from its step config and summary, under
  OrthogonalSettings' names: `lambda_relative` (set when λ was given as a multiple of ‖∇ action
  loss‖/‖γ‖) and `lambda_absolute` (the λ the run used, measured from the relative form where that was
  set); runs recorded before the two names existed are read from their `weight`/`scale` fields;
- α: the `alpha` of the `vector` edge into its `init` (θ_meta = θ_pt + α·γ);
- `success@<budget>`: the mean over tasks, and `<task>@<budget>` per task, of the latest evaluation of
  the checkpoint it had at that budget (a snapshot, or the final one at `steps`), under one evaluation
  protocol (`--fingerprint`, as `capvector scores` takes it; by default the test protocol with the most
  evaluations, the others named below the table). A task's column never mixes protocols.

Success is a fraction in csv, json and parquet (as in the catalogue) and a percentage in the table.
Nothing here imports pandas, torch, prefect or metaworld. `export --format lerobot` (a dataset artifact as a
LeRobotDataset v3.0 folder) imports its code (capvector.tasks.lerobot_dataset) when it runs.
"""

from __future__ import annotations

import csv
import io
import json
import sys
from pathlib import Path
from typing import Annotated, Any

import typer

from capvector.flows.evaluation.protocols import NAMES, SHOWN, Protocol, listing, protocols, resolve
from capvector.flows.runtime.home import resolve_home

STAGES = ("pretrain", "extraction", "tuning", "sweep", "downstream", "other")
FORMATS = ("table", "csv", "json", "parquet")

# Every trained run (`runs`) and the checkpoint it had at each budget (`points`).
RUNS_WITH = r"""
WITH trained AS (
    SELECT id, name, created_at, code_version, config->'train_step' AS ts, config->'summary' AS summary
    FROM artifacts
    WHERE kind = 'checkpoint' AND (config->'train_step') IS NOT NULL AND (config->>'of_run') IS NULL
), starts AS (
    SELECT e.child AS run_id, e.parent, e.role, p.name
    FROM edges e SEMI JOIN trained t ON t.id = e.child LEFT JOIN artifacts p ON p.id = e.parent
    WHERE e.role IN ('init', 'regularized_by')
), alphas AS (
    SELECT run_id, CASE WHEN min(alpha) = max(alpha) THEN min(alpha) END AS alpha FROM (
        SELECT s.run_id, TRY_CAST(v.attrs->>'alpha' AS DOUBLE) AS alpha
        FROM starts s JOIN edges v ON v.child = s.parent AND v.role = 'vector'
        WHERE s.role = 'init'
    ) GROUP BY run_id
), start_draws AS (
    SELECT run_id,
        min(TRY_CAST(NULLIF(regexp_extract(name, '\bdraw (\d+)\b', 1), '') AS INTEGER)) AS draw,
        min(TRY_CAST(NULLIF(regexp_extract(name, '\breplicate (\d+)\b', 1), '') AS INTEGER)) AS replicate
    FROM starts GROUP BY run_id
), study_reach AS MATERIALIZED (
    WITH RECURSIVE reach(study, node) AS (
        SELECT regexp_extract(name, '^analyse study (.*?)( \(gate\))?$', 1), id FROM artifacts
        WHERE kind = 'study'
        UNION
        SELECT r.study, e.parent FROM reach r JOIN edges e ON e.child = r.node
    ) SELECT * FROM reach
), run_studies AS (
    SELECT t.id AS run_id, string_agg(DISTINCT r.study, ', ' ORDER BY r.study) AS study
    FROM trained t JOIN study_reach r ON r.node = t.id GROUP BY t.id
), flow_runs AS (
    SELECT a.id AS run_id, f.state AS status,
        CASE WHEN f.flow_name = 'study' THEN f.parameters->'config'->>'name' END AS study
    FROM artifacts a JOIN runs f ON f.flow_run_id = a.flow_run_id SEMI JOIN trained t ON t.id = a.id
), staged AS (
    SELECT *, CASE
        WHEN regexp_matches(name, '^downstream \S+ ((draw|replicate) \d+ )?seed') THEN 'downstream'
        WHEN starts_with(name, 'tune ') THEN 'tuning'
        WHEN contains(name, 'θ_pt') THEN 'pretrain'
        WHEN regexp_matches(name, 'θ_(ft|ao)') THEN 'extraction'
        WHEN regexp_matches(name, '^\S+ α=') THEN 'sweep'
        ELSE 'other' END AS stage
    FROM trained
), runs AS (
    SELECT
        t.id, t.name, t.stage,
        CASE t.stage
            WHEN 'downstream' THEN regexp_extract(t.name, '^downstream (\S+) ', 1)
            WHEN 'tuning' THEN regexp_extract(t.name, '^tune (\S+)', 1)
            WHEN 'sweep' THEN regexp_extract(t.name, '^(\S+) α=', 1)
            WHEN 'other' THEN NULL
            ELSE regexp_extract(t.name, 'θ_(pt|ft|ao)', 0) END AS arm,
        coalesce(
            TRY_CAST(NULLIF(regexp_extract(t.name, '\bdraw (\d+)\b', 1), '') AS INTEGER), d.draw
        ) AS draw,
        coalesce(
            TRY_CAST(NULLIF(regexp_extract(t.name, '\breplicate (\d+)\b', 1), '') AS INTEGER), d.replicate
        ) AS replicate,
        coalesce(f.study, s.study) AS study,
        f.status,
        round(
            (TRY_CAST(t.summary->>'steps' AS DOUBLE)
                - coalesce(TRY_CAST(t.summary->>'resumed_from_step' AS DOUBLE), 0))
            / NULLIF(TRY_CAST(t.summary->>'steps_per_s' AS DOUBLE), 0), 1
        ) AS train_s,
        TRY_CAST(t.ts->'train'->>'seed' AS BIGINT) AS seed,
        a.alpha,
        coalesce(
            TRY_CAST(t.ts->'orthogonal'->>'lambda_relative' AS DOUBLE),
            CASE WHEN t.ts->'orthogonal'->>'scale' = 'action_gradient'
                THEN TRY_CAST(t.ts->'orthogonal'->>'weight' AS DOUBLE) END
        ) AS lambda_relative,
        coalesce(
            TRY_CAST(t.summary->>'lambda_absolute' AS DOUBLE),
            TRY_CAST(t.summary->>'orthogonal_lambda' AS DOUBLE)
        ) AS lambda_absolute,
        TRY_CAST(t.ts->'train'->>'lr' AS DOUBLE) AS lr,
        t.ts->>'adapter' AS adapter,
        TRY_CAST(t.ts->'train'->>'steps' AS BIGINT) AS steps,
        t.ts->'train'->'aux'->>'name' AS aux,
        TRY_CAST(t.ts->'train'->'aux'->>'weight' AS DOUBLE) AS aux_weight,
        t.code_version AS code_revision,
        t.created_at
    FROM staged t LEFT JOIN alphas a ON a.run_id = t.id LEFT JOIN start_draws d ON d.run_id = t.id
    LEFT JOIN flow_runs f ON f.run_id = t.id LEFT JOIN run_studies s ON s.run_id = t.id
), points AS (
    SELECT id AS run_id, steps AS budget, id AS checkpoint_id FROM runs
    UNION ALL
    SELECT e.child, TRY_CAST(e.attrs->>'budget' AS BIGINT), e.parent
    FROM edges e SEMI JOIN runs r ON r.id = e.child
    WHERE e.role = 'snapshot'
)"""
RUN_COLUMNS = (
    "id, name, study, stage, arm, draw, replicate, seed, alpha, lambda_relative, lambda_absolute, "
    "lr, adapter, steps, aux, aux_weight, status, train_s, code_revision"
)
SCORED_WITH = """, scores AS (
    SELECT p.run_id, p.budget, t.task, arg_max(t.success_rate, t.evaluated_at) AS success
    FROM points p JOIN eval_tasks t ON t.checkpoint_id = p.checkpoint_id
    WHERE list_contains($fingerprints::VARCHAR[], t.fingerprint)
    GROUP BY p.run_id, p.budget, t.task
)"""


def _ident(name: str) -> str:
    return '"' + name.replace('"', '""') + '"'


def _open(home: str | None):
    from capvector.artifacts.api import ArtifactsAPI

    return ArtifactsAPI(resolve_home(home))


def _evaluated(api: Any, fingerprints: list[str] | None = None) -> list[tuple[int, str, str]]:
    """(budget, task, fingerprint) of every evaluation of a run's checkpoints (under `fingerprints`)."""
    where = "" if fingerprints is None else "WHERE list_contains($fingerprints::VARCHAR[], t.fingerprint)"
    _, rows = api.query_rows(
        RUNS_WITH + " SELECT DISTINCT p.budget, t.task, t.fingerprint "
        f"FROM points p JOIN eval_tasks t ON t.checkpoint_id = p.checkpoint_id {where} ORDER BY ALL",
        None if fingerprints is None else {"fingerprints": fingerprints},
    )
    return rows


def choose_protocols(api: Any, choice: str | None) -> list[Protocol]:
    """The protocols the success columns are read under.

    `test` or `validation`: every protocol starting at that goal-seed base (a study has one per task
    set, e.g. validation on D_ext and on D_down); a fingerprint or a unique prefix of 6+ characters:
    that one (capvector.flows.evaluation.protocols.resolve). Without a choice: `test` when anything was
    evaluated on the test goals (the one with the most evaluations where several were: one protocol per table
    unless asked, `others_note` names the rest), else the one protocol there is; several others are an error
    listing them. Two chosen protocols that evaluated the same task are an error too: a column never mixes
    protocols."""
    choices = protocols(api, {fp for _, _, fp in _evaluated(api)})
    if not choices:
        if choice is not None:
            resolve(choice, choices, "the catalogue")  # raises: names what there is (nothing)
        return []
    key = None if choice is None else choice.strip().lower()
    if key is None:  # one protocol per table unless asked: the test protocol most evaluations used
        tests = sorted((p for p in choices if p.name == "test"), key=lambda p: -p.evaluations)
        chosen = tests[:1] or (choices if len(choices) == 1 else [])
        if not chosen:
            raise ValueError(
                f"the runs were evaluated under {len(choices)} protocols and none on the test goals: "
                f"{listing(choices)}; choose with --fingerprint validation or a fingerprint prefix"
            )
    elif key in NAMES:
        chosen = [p for p in choices if p.seed_base == NAMES[key]]
        if not chosen:
            resolve(choice, choices, "the catalogue")  # raises, listing the protocols there are
    else:
        fp = resolve(choice, choices, "the catalogue")
        chosen = [p for p in choices if p.fingerprint == fp]
    by_task: dict[str, set[str]] = {}
    for _, task, fp in _evaluated(api, [p.fingerprint for p in chosen]):
        by_task.setdefault(task, set()).add(fp)
    mixed = {t: fps for t, fps in by_task.items() if len(fps) > 1}
    if mixed:
        task, fps = sorted(mixed.items())[0]
        raise ValueError(
            f"task {task} was evaluated under {len(fps)} of the chosen protocols, never shown in one "
            f"column: {listing([p for p in chosen if p.fingerprint in fps])}; choose one with "
            "--fingerprint and a fingerprint prefix"
        )
    return chosen


def others_note(api: Any, chosen: list[Protocol]) -> list[str]:
    """A line naming the test protocols the default table left out, when there are any."""
    shown = {p.fingerprint for p in chosen}
    left = [p for p in protocols(api, {fp for _, _, fp in _evaluated(api)}) if p.name == "test"]
    left = [p for p in left if p.fingerprint not in shown]
    if not left:
        return []
    return [
        f"not shown: {listing(left)} (one protocol per table: --fingerprint test for every test protocol, "
        "or a fingerprint prefix)"
    ]


def runs_select(
    api: Any,
    fingerprints: list[str],
    arms: list[str] = (),
    stages: list[str] = (),
    where: str | None = None,
    per_task: bool = True,
) -> tuple[str, dict[str, Any]]:
    """The runs table as one SELECT and its parameters (for `query_rows` or `copy_to`)."""
    cells = _evaluated(api, fingerprints) if fingerprints else []
    budgets = sorted({b for b, _, _ in cells if b is not None})
    params: dict[str, Any] = {"fingerprints": fingerprints, "arms": list(arms), "stages": list(stages)}
    columns = [f"avg(success) FILTER (WHERE budget = {int(b)}) AS {_ident(f'success@{b}')}" for b in budgets]
    if per_task:
        for i, (b, task) in enumerate(sorted({(b, t) for b, t, _ in cells if b is not None})):
            params[f"task_{i}"] = task
            name = _ident(f"{task}@{b}")
            columns.append(f"max(success) FILTER (WHERE budget = {int(b)} AND task = $task_{i}) AS {name}")
    names = [c.rsplit(" AS ", 1)[1] for c in columns]
    wide = f"SELECT run_id, {', '.join(columns)} FROM scores GROUP BY run_id" if columns else None
    sql = RUNS_WITH + SCORED_WITH
    if wide:
        sql += f", wide AS ({wide})"
    joined = ", ".join([*(f"r.{c.strip()}" for c in RUN_COLUMNS.split(",")), *(f"w.{n}" for n in names)])
    sql += f""", tabled AS (
    SELECT {joined}, r.created_at FROM runs r {"LEFT JOIN wide w ON w.run_id = r.id" if wide else ""}
)
SELECT * FROM tabled
WHERE (len($arms::VARCHAR[]) = 0 OR list_contains($arms::VARCHAR[], arm))
  AND (len($stages::VARCHAR[]) = 0 OR list_contains($stages::VARCHAR[], stage))
  AND ({where or "TRUE"})
ORDER BY list_position({list(STAGES)!r}, stage), arm, draw NULLS FIRST, seed, created_at, id"""
    return sql, params


def _split(values: list[str] | None) -> list[str]:
    return [v.strip() for item in values or [] for v in item.split(",") if v.strip()]


def _cell(column: str, value: Any) -> str:
    if value is None:
        return ""
    if "@" in column and isinstance(value, float):
        return f"{100 * value:.1f}%"
    if column == "id":
        return value[:SHOWN]
    if column == "created_at":
        return str(value)[:19]
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def render_table(columns: list[str], rows: list[tuple]) -> str:
    """Plain aligned text, numbers (and percentages) to the right; no pandas, no truncation."""
    cells = [[_cell(c, v) for c, v in zip(columns, row, strict=True)] for row in rows]
    right = [
        bool(rows) and all(isinstance(r[i], int | float) or r[i] is None for r in rows)
        for i in range(len(columns))
    ]
    widths = [max([len(c), *(len(r[i]) for r in cells)]) for i, c in enumerate(columns)]

    def line(values: list[str]) -> str:
        return "  ".join(
            v.rjust(w) if r else v.ljust(w) for v, w, r in zip(values, widths, right, strict=True)
        )

    return "\n".join(line(v).rstrip() for v in [columns, *cells])


def _csv_text(columns: list[str], rows: list[tuple]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    writer.writerows([["" if v is None else v for v in row] for row in rows])
    return buffer.getvalue()


def _say(text: str, to_stderr: bool) -> None:
    typer.echo(text, err=to_stderr)


HomeOption = Annotated[str | None, typer.Option("--home", help="capvector home (default: $CAPVECTOR_HOME)")]
FingerprintOption = Annotated[
    str | None,
    typer.Option(
        "--fingerprint",
        help="the evaluation protocol of the success columns: test (default when there is one), "
        "validation, or a fingerprint (a unique prefix of 6+ characters)",
    ),
]


def runs(
    arm: Annotated[
        list[str] | None, typer.Option("--arm", help="only these arms (repeatable or comma-separated)")
    ] = None,
    stage: Annotated[
        list[str] | None,
        typer.Option("--stage", "--kind", help=f"only these stages: {' | '.join(STAGES)} (repeatable)"),
    ] = None,
    where: Annotated[
        str | None,
        typer.Option(
            "--where",
            help='an SQL condition on the table\'s columns, e.g. "seed = 0 AND lr < 1e-3" or '
            '"\\"success@500\\" > 0.5"',
        ),
    ] = None,
    fingerprint: FingerprintOption = None,
    means_only: Annotated[
        bool,
        typer.Option("--means-only", help="success@<budget> (mean over tasks) only, no per-task columns"),
    ] = False,
    fmt: Annotated[str, typer.Option("--format", help=" | ".join(FORMATS))] = "table",
    out: Annotated[
        Path | None, typer.Option("-o", "--out", help="write here (csv, json; required for parquet)")
    ] = None,
    home: HomeOption = None,
    as_json: Annotated[
        bool, typer.Option("--json", help="print machine-readable JSON (--format json)")
    ] = False,
) -> None:
    """The experiment table: one row per trained run (arm, draw, seed, α, λ, lr, adapter, steps) with
    its success at every budget and task, from the evaluations of its checkpoint and its snapshots."""
    if as_json and fmt not in ("table", "json"):
        raise typer.BadParameter(f"--json prints JSON: give it or --format {fmt}, not both")
    fmt = "json" if as_json else fmt
    if fmt not in FORMATS:
        raise typer.BadParameter(f"unknown format {fmt!r}; use {', '.join(FORMATS)}")
    if fmt == "parquet" and out is None:
        raise typer.BadParameter("--format parquet writes a file: give -o FILE")
    if fmt == "table" and out is not None:
        raise typer.BadParameter("-o writes csv, json or parquet: give --format too")
    stages = _split(stage)
    unknown = sorted(set(stages) - set(STAGES))
    if unknown:
        raise typer.BadParameter(f"unknown stage {', '.join(unknown)}; use {', '.join(STAGES)}")
    api = _open(home)
    chosen = choose_protocols(api, fingerprint)
    sql, params = runs_select(
        api, [p.fingerprint for p in chosen], _split(arm), stages, where, per_task=not means_only
    )
    notes = [f"protocol {p.describe()}" for p in chosen] or ["no evaluations: no success columns"]
    notes += others_note(api, chosen) if fingerprint is None else []
    if fmt == "parquet":
        n = api.copy_to(sql, params, out, "parquet")
        _say(f"wrote {out}: {n} runs", False)
        for line in notes:
            _say(line, False)
        return
    columns, rows = api.query_rows(sql, params)
    if fmt == "table":
        typer.echo(render_table(columns, rows))
        for line in notes:
            typer.echo(line)
        return
    if fmt == "csv":
        text = _csv_text(columns, rows)
    else:
        text = json.dumps([dict(zip(columns, r, strict=True)) for r in rows], indent=1, default=str) + "\n"
    if out is None:
        sys.stdout.write(text)
    else:
        out.write_text(text)
        _say(f"wrote {out}: {len(rows)} runs", True)
    for line in notes:
        _say(line, True)  # stdout holds the data alone


def _protocols_with() -> str:
    cases = " ".join(f"WHEN {base} THEN '{name}'" for name, base in NAMES.items())
    return f""", protocols AS (
    SELECT fingerprint, min(seed) AS seed_base, CASE min(seed) {cases} END AS protocol
    FROM eval_episodes GROUP BY fingerprint
), homes AS (
    SELECT checkpoint_id, min(run_id) AS run_id, min(budget) AS budget FROM points GROUP BY checkpoint_id
)"""


EPISODES_SELECT = """
SELECT e.evaluation_id, e.checkpoint_id, h.run_id, h.budget, e.task, e.episode, e.seed AS goal_seed,
       e.success, e.steps, e."return", e.fingerprint, p.protocol, e.evaluated_at
FROM eval_episodes e LEFT JOIN homes h ON h.checkpoint_id = e.checkpoint_id
LEFT JOIN protocols p ON p.fingerprint = e.fingerprint
ORDER BY e.evaluated_at, e.evaluation_id, e.episode"""
EVALUATIONS_SELECT = """
SELECT t.evaluation_id, t.checkpoint_id, a.name AS checkpoint_name, h.run_id, h.budget, t.task,
       t.fingerprint, p.protocol, p.seed_base, t.n_episodes, t.success_rate, t.mean_return, t.mean_steps,
       t.evaluated_at
FROM eval_tasks t LEFT JOIN homes h ON h.checkpoint_id = t.checkpoint_id
LEFT JOIN artifacts a ON a.id = t.checkpoint_id LEFT JOIN protocols p ON p.fingerprint = t.fingerprint
ORDER BY t.evaluated_at, t.evaluation_id, t.task"""


EXPORT_FORMATS = ("tables", "lerobot")


def export(
    directory: Annotated[Path, typer.Argument(help="folder to write into (created)")],
    fmt: Annotated[
        str, typer.Option("--format", help="tables (Parquet tables of the catalogue) | lerobot (a dataset)")
    ] = "tables",
    dataset: Annotated[
        str | None,
        typer.Option("--dataset", help="with --format lerobot: the dataset artifact (id or prefix)"),
    ] = None,
    fingerprint: FingerprintOption = None,
    home: HomeOption = None,
    as_json: Annotated[bool, typer.Option("--json", help="print what was written as JSON")] = False,
) -> None:
    """Episodes, evaluations and runs as Parquet files (DuckDB's COPY), for pandas, polars, R or DuckDB;
    or, with `--format lerobot --dataset ID`, a demonstration dataset as a LeRobotDataset v3.0 folder.

    tables (default): episodes.parquet: one row per episode (evaluation, checkpoint, its run and budget,
    task, goal seed, success, steps, return, protocol); evaluations.parquet: one row per evaluation and
    task (success rate, episodes, protocol, run and budget); runs.parquet: the `capvector runs` table
    under --fingerprint (success as a fraction).

    lerobot: meta/info.json, stats.json, tasks.parquet (the instructions), meta/episodes and data
    Parquet files in LeRobot's v3.0 layout, into DIR (new or empty); `capvector import-dataset` reads
    it back."""
    if fmt not in EXPORT_FORMATS:
        raise typer.BadParameter(f"unknown format {fmt!r}; use {' or '.join(EXPORT_FORMATS)}")
    if fmt == "lerobot":
        if dataset is None:
            raise typer.BadParameter("--format lerobot exports a dataset: give --dataset ID")
        if fingerprint is not None:
            raise typer.BadParameter(
                "--fingerprint chooses the runs table's protocol: not for --format lerobot"
            )
        _export_lerobot(directory, dataset, home, as_json)
        return
    if dataset is not None:
        raise typer.BadParameter("--dataset goes with --format lerobot")
    _export_tables(directory, fingerprint, home, as_json)


def _export_lerobot(directory: Path, dataset: str, home: str | None, as_json: bool) -> None:
    from capvector.tasks.lerobot_dataset import export_dataset
    from capvector.tasks.runtime.workspace import Workspace

    written = export_dataset(Workspace(resolve_home(home)), dataset, directory)
    if as_json:
        typer.echo(json.dumps(written, indent=1))
        return
    typer.echo(
        f"wrote {written['path']}: LeRobotDataset v3.0 of dataset {written['dataset'][:SHOWN]}, "
        f"{written['total_episodes']} episodes, {written['total_frames']} frames, {written['total_tasks']} "
        f"tasks at {written['fps']} fps"
    )


def _export_tables(directory: Path, fingerprint: str | None, home: str | None, as_json: bool) -> None:
    api = _open(home)
    chosen = choose_protocols(api, fingerprint)
    runs_sql, runs_params = runs_select(api, [p.fingerprint for p in chosen])
    directory.mkdir(parents=True, exist_ok=True)
    written = {}
    with_points = RUNS_WITH + _protocols_with()
    for name, sql, params, what in [
        ("episodes", with_points + EPISODES_SELECT, None, "one per episode"),
        ("evaluations", with_points + EVALUATIONS_SELECT, None, "one per evaluation and task"),
        ("runs", runs_sql, runs_params, "one per trained run"),
    ]:
        path = directory / f"{name}.parquet"
        written[name] = {"path": str(path), "rows": api.copy_to(sql, params, path, "parquet"), "grain": what}
    if as_json:
        typer.echo(json.dumps({**written, "protocols": [p.fingerprint for p in chosen]}, indent=1))
        return
    for item in written.values():
        typer.echo(f"wrote {item['path']}: {item['rows']} rows ({item['grain']})")
    for p in chosen:
        typer.echo(f"runs.parquet success columns: protocol {p.describe()}")
