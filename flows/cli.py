"""The `capvector` command line: run the recipe, inspect lineage and scores, operate on vectors.

Imports here stay light: `--help` and the read-only commands (sql, lineage, scores, artifacts, verify,
catalogue) load neither torch, pandas, prefect nor metaworld; every command imports what it runs.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import typer

from artifacts.errors import ArtifactError
from flows.catalogue_commands import catalogue_app
from flows.config_command import config_app
from flows.home import resolve_home, set_root_home
from flows.lineage_views import as_mermaid, as_tree, keep_kinds
from flows.table_commands import export, runs
from flows.verify_command import verify

app = typer.Typer(no_args_is_help=True, add_completion=False, help=__doc__)
artifacts_app = typer.Typer(no_args_is_help=True, help="List and show artifacts.")
vector_app = typer.Typer(
    no_args_is_help=True, help="Capability-vector arithmetic on safetensors checkpoints."
)
app.add_typer(artifacts_app, name="artifacts")
app.add_typer(vector_app, name="vector")
app.add_typer(catalogue_app, name="catalogue")
app.add_typer(config_app, name="config")
app.command("verify")(verify)
app.command("runs")(runs)
app.command("export")(export)


def _leave_ctrl_c_to_the_cli() -> None:
    """In a step worker, ignore SIGINT: the CLI stops its workers on Ctrl-C (main()), and a worker
    taking the terminal's SIGINT itself would print a KeyboardInterrupt traceback. A spawned worker
    runs this module (as its `__mp_main__`, or through the console script) first thing, before it
    imports Prefect or torch, so it ignores Ctrl-C from its first moments (~0.1 s in). Costs the CLI
    nothing: it only looks at modules already loaded."""
    mp = sys.modules.get("multiprocessing")
    if mp is not None and mp.current_process().name != "MainProcess":
        with contextlib.suppress(ValueError):  # not imported from a main thread: leave it
            signal.signal(signal.SIGINT, signal.SIG_IGN)


_leave_ctrl_c_to_the_cli()


class _LazyConsole:
    """A rich Console made on first use: `sql` and `--help` never need rich's import (~30 ms)."""

    def __init__(self, **options: Any):
        self._options, self._console = options, None

    def __getattr__(self, name: str) -> Any:
        if self._console is None:
            from rich.console import Console

            self._console = Console(**self._options)
        return getattr(self._console, name)


def Table(*columns: str) -> Any:  # noqa: N802 (stands for rich.table.Table, imported when a table is made)
    from rich.table import Table as RichTable

    return RichTable(*columns)


console = _LazyConsole()
err = _LazyConsole(stderr=True)

HomeOption = Annotated[str | None, typer.Option("--home", help="capvector home (default: $CAPVECTOR_HOME)")]
JsonOption = Annotated[bool, typer.Option("--json", help="print machine-readable JSON")]
SetOption = Annotated[list[str] | None, typer.Option("--set", help="override a config key: a.b=value")]
DryRunOption = Annotated[
    bool, typer.Option("--dry-run", help="print the plan's steps, cached or to run, and run nothing")
]
# Where the steps run (flows.runners): the same five options on run, study, sweep, evaluate, reevaluate.
_RUNNER_PANEL = "Where steps run"
RunnerOption = Annotated[
    str | None,
    typer.Option(
        "--runner",
        help="process (a pool of --workers, default) | dask | ray; evaluate, reevaluate: thread (default)",
        rich_help_panel=_RUNNER_PANEL,
    ),
]
AddressOption = Annotated[
    str | None,
    typer.Option(
        help="dask: tcp://host:port of a running scheduler; ray: its address", rich_help_panel=_RUNNER_PANEL
    ),
]
WorkersOption = Annotated[
    int, typer.Option(help="worker processes of a pool or a local cluster", rich_help_panel=_RUNNER_PANEL)
]
ClusterClassOption = Annotated[
    str | None,
    typer.Option(
        help="dask: a cluster class to start, e.g. dask_jobqueue.SLURMCluster", rich_help_panel=_RUNNER_PANEL
    ),
]
ClusterKwargsOption = Annotated[
    str | None,
    typer.Option(help="dask: that cluster's keyword arguments, JSON", rich_help_panel=_RUNNER_PANEL),
]


class State:
    debug: bool = os.environ.get("CAPVECTOR_DEBUG", "").lower() not in ("", "0", "false")


# Commands that run a flow: they get the run's one Prefect API server (flows.run_server). Its address
# is reserved before Prefect is imported; the process starts when a flow is sure to run.
FLOW_COMMANDS = {"run", "study", "calibrate", "evaluate", "reevaluate", "sweep", "schedule"}


@app.callback()
def main_options(
    ctx: typer.Context,
    home: Annotated[
        str | None, typer.Option("--home", envvar="CAPVECTOR_HOME", help="capvector home")
    ] = None,
    debug: Annotated[
        bool,
        typer.Option("--debug", envvar="CAPVECTOR_DEBUG", help="show tracebacks and run logs on errors"),
    ] = False,
) -> None:
    """capvector: capability vectors for VLA policies on Meta-World, with lineage."""
    set_root_home(home)
    State.debug = State.debug or debug
    if State.debug:
        os.environ["CAPVECTOR_DEBUG"] = "1"  # step workers inherit it
    if ctx.invoked_subcommand in FLOW_COMMANDS:
        from flows.run_server import start_run_server

        start_run_server()  # the address only: a run the content cache answers never starts the server


def _boot_server() -> None:
    """Spawn the run's reserved Prefect server now, so that it boots while the command imports torch
    and the flows: for a command sure to run a flow (evaluate, reevaluate, sweep; run and study on a
    new home). Otherwise `_preflight` starts it, once the content cache has not answered the plan."""
    from flows.run_server import start_server_now

    start_server_now()


def _new_home(home: str | None, dry_run: bool) -> bool:
    """A local home that does not exist yet, for a run that is not a dry run: nothing is cached."""
    if dry_run:
        return False
    from artifacts.home import is_local

    home = resolve_home(home)
    return is_local(home) and not Path(home).exists()


def _workspace(home: str | None):
    """A fresh Workspace per call: opening it is what catches the catalogue up with the store."""
    from tasks.workspace import Workspace

    return Workspace(resolve_home(home))


def _print_json(data: Any) -> None:
    console.print_json(json.dumps(data, default=str))


def _preflight(command: str, home: str | None) -> None:
    """Before any flow: the run's Prefect server is started (if not yet) and up (a configured but
    unreachable one is an error naming its address, not a hang); progress goes to a log file as well
    as the terminal."""
    from flows.run_server import wait_for_api
    from tasks.prefect_task import quiet_failed_run_logs

    wait_for_api()  # first: an unreachable server must leave no home behind
    _start_log(command, home)
    quiet_failed_run_logs()  # main() prints a failing run's error, in one line


def _start_log(command: str, home: str | None) -> None:
    """Progress to a log file in the home as well as the terminal (step workers inherit the path)."""
    from tasks.progress import LOG_FILE_ENV, emit

    if not os.environ.get(LOG_FILE_ENV):
        from datetime import UTC, datetime

        logs = _workspace(home).local_root / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
        slug = "-".join(command.replace("--preset", "").split())
        os.environ[LOG_FILE_ENV] = str(logs / f"{slug}-{stamp}-{os.getpid()}.log")
        from flows.housekeeping import prune_on_start

        prune_on_start(resolve_home(home))  # logs stay bounded (~2 ms; the new one is always kept)
    emit(f"capvector {command}: home {resolve_home(home)}, log {os.environ[LOG_FILE_ENV]}")


def _from_cache(command: str, home: str, plan, total: int, label: str, dry_run: bool = False):
    """Know before starting: the plan's result when the content cache answers every step (no Prefect
    run, server wait or worker), else None. `dry_run` prints the plan's cache status and exits."""
    from flows.steps import CacheProbe, NotAllCached

    if _new_home(home, dry_run):
        return None  # a new home caches nothing (and an unreachable server must leave none behind)
    probe = CacheProbe(home, total, label)
    try:
        result, missing = plan(probe), None
    except NotAllCached as exc:
        result, missing = None, str(exc)
    if dry_run:
        for step, artifact_id in probe.answered:
            typer.echo(f"cached  {artifact_id[:12]}  {step}")
        if missing is None:
            typer.echo(f"all {total} steps cached: `capvector {command}` prints its result at once")
        else:
            todo = total - len(probe.answered)
            typer.echo(f"to run  {missing}, then what depends on it ({todo} of {total} steps to run)")
        raise typer.Exit(0)
    if missing is None:
        _start_log(command, home)
        probe.replay()
    return result


def _runner(
    runner: str | None,
    address: str | None,
    workers: int,
    cluster_class: str | None,
    cluster_kwargs: str | None,
    default: str = "process",
):
    """The runner options, checked before anything runs (a bad one exits 2 naming the problem)."""
    from flows.runners import runner_config

    kind = runner or default
    if kind == "thread" and default != "thread":
        raise ValueError("--runner thread is for evaluate and reevaluate: training steps need processes")
    return runner_config(kind, address, workers, cluster_class, cluster_kwargs)


def _answer_or_run(
    command: str,
    home: str | None,
    plan,
    total: int,
    label: str,
    dry_run: bool,
    flow_fn,
    config,
    runner_config,
) -> Any:
    """A planned command's result: from the content cache when it answers every step (no server, no
    flow run), else from a flow run (server up, log opened, tagged with the command and preset)."""
    result = _from_cache(command, resolve_home(home), plan, total, label, dry_run)
    if result is None:
        from flows.runs import run_tags

        _preflight(command, home)
        with run_tags(command.split()[0], config.name):
            result = _on_runner(flow_fn, runner_config)(config.model_dump(mode="json"), resolve_home(home))
    return result


def _on_runner(flow_fn: Any, config: Any) -> Any:
    from flows.runners import build_runner

    return flow_fn.with_options(task_runner=build_runner(config))


# ---------------------------------------------------------------------------- flows
@app.command()
def run(
    preset: Annotated[str, typer.Option(help="smoke | quick | paper | path to a YAML file")] = "quick",
    overrides: SetOption = None,
    home: HomeOption = None,
    as_json: JsonOption = False,
    dry_run: DryRunOption = False,
    runner: RunnerOption = None,
    address: AddressOption = None,
    workers: WorkersOption = 2,
    cluster_class: ClusterClassOption = None,
    cluster_kwargs: ClusterKwargsOption = None,
) -> None:
    """Run the whole recipe (cached): demos -> θ_pt -> θ_ft, θ_ao -> γ -> θ_meta -> arms -> eval -> report."""
    if _new_home(home, dry_run):
        _boot_server()
    from flows.config import load_config
    from flows.pipeline import pipeline, pipeline_steps, run_pipeline

    runner_config = _runner(runner, address, workers, cluster_class, cluster_kwargs)
    config = load_config(preset, overrides)
    home = resolve_home(home)
    command = f"run --preset {preset}"
    plan = lambda steps: run_pipeline(steps, config)  # noqa: E731
    label = f"pipeline {config.name}"
    ids = _answer_or_run(
        command, home, plan, pipeline_steps(config), label, dry_run, pipeline, config, runner_config
    )
    if as_json:
        _print_json(ids)
        return
    from tasks.reporting import load_report, markdown_table, timings

    workspace = _workspace(home)
    report = load_report(workspace, ids["report"])
    console.print(markdown_table(report, timings(workspace, report)))  # speeds: from the records
    console.print(f"report: {ids['report']}   (capvector report {ids['report'][:12]})")


@app.command()
def evaluate(
    checkpoints: Annotated[list[str], typer.Argument(help="checkpoint artifact ids (or unique prefixes)")],
    tasks: Annotated[str, typer.Option(help="comma-separated Meta-World task names")],
    episodes: Annotated[int, typer.Option(help="episodes (goal variations) per task")] = 20,
    horizon: int = 500,
    execute_steps: Annotated[int, typer.Option(help="actions executed per predicted chunk")] = 1,
    obs_mode: str = "state",
    camera: Annotated[str, typer.Option(help="pixels: camera (another tests generalization)")] = "corner2",
    image_size: Annotated[int, typer.Option(help="image side for pixels policies")] = 64,
    video: Annotated[int, typer.Option(help="episodes per task recorded as GIF video artifacts")] = 0,
    runner: RunnerOption = None,
    address: AddressOption = None,
    workers: WorkersOption = 2,
    cluster_class: ClusterClassOption = None,
    cluster_kwargs: ClusterKwargsOption = None,
    home: HomeOption = None,
    as_json: JsonOption = False,
) -> None:
    """Evaluate checkpoints on any tasks under one protocol (test seeds, disjoint from demo seeds)."""
    _boot_server()
    from capvector_core.evaluation import EvalConfig
    from flows.evaluation_flows import evaluate_flow

    runner_config = _runner(runner, address, workers, cluster_class, cluster_kwargs, default="thread")
    _preflight("evaluate", home)
    config = EvalConfig(
        tasks=[t.strip() for t in tasks.split(",") if t.strip()],
        episodes_per_task=episodes,
        horizon=horizon,
        execute_steps=execute_steps,
        obs_mode=obs_mode,
        camera=camera,
        image_size=image_size,
        record_video=video,
    )
    flow_fn = _on_runner(evaluate_flow, runner_config)
    from flows.runs import run_tags

    with run_tags("evaluate"):
        result = flow_fn(resolve_home(home), checkpoints, config.model_dump(mode="json"))
    from artifacts.scores import read_scores

    scores = {s.evaluation_id: s for s in read_scores(_workspace(home).api, evaluations=result.values())}
    if as_json:
        _print_json([{"checkpoint": c, "evaluation": e, **scores[e].model_dump()} for c, e in result.items()])
        return
    table = Table("checkpoint", "evaluation", "mean success", "per task")
    for c, e in result.items():
        per_task = ", ".join(f"{t}: {100 * v:.0f}%" for t, v in scores[e].success_rates.items())
        table.add_row(c[:12], e[:12], f"{100 * scores[e].mean_success:.1f}%", per_task)
    console.print(table)


@app.command()
def reevaluate(
    query: Annotated[
        str | None, typer.Option(help="read-only SQL whose first column is checkpoint ids")
    ] = None,
    home: HomeOption = None,
    as_json: JsonOption = False,
    runner: RunnerOption = None,
    address: AddressOption = None,
    workers: WorkersOption = 2,
    cluster_class: ClusterClassOption = None,
    cluster_kwargs: ClusterKwargsOption = None,
) -> None:
    """Re-run the evaluations of the selected checkpoints under the installed library versions."""
    _boot_server()
    from flows.evaluation_flows import DEFAULT_SELECTION, reevaluate_flow, summary_markdown

    runner_config = _runner(runner, address, workers, cluster_class, cluster_kwargs, default="thread")
    _preflight("reevaluate", home)
    from flows.runs import run_tags

    with run_tags("reevaluate"):
        changes = _on_runner(reevaluate_flow, runner_config)(resolve_home(home), query or DEFAULT_SELECTION)
    if as_json:
        _print_json(changes)
    else:
        console.print(summary_markdown(changes) if changes else "nothing selected")


@app.command()
def study(
    preset: Annotated[
        str,
        typer.Option(help="study-control-small | study-control | study-state | study-pixels | a YAML path"),
    ] = "study-control-small",
    overrides: SetOption = None,
    home: HomeOption = None,
    report: Annotated[
        Path | None,
        typer.Option(help="write the Markdown report and its figures here (default: <home>/reports/)"),
    ] = None,
    as_json: JsonOption = False,
    dry_run: DryRunOption = False,
    runner: RunnerOption = None,
    address: AddressOption = None,
    workers: WorkersOption = 2,
    cluster_class: ClusterClassOption = None,
    cluster_kwargs: ClusterKwargsOption = None,
) -> None:
    """Run an experiment: selections on validation goals, preconditions, all arms, analysis, report."""
    if _new_home(home, dry_run):
        _boot_server()
    from functools import partial

    from flows.study import plan_study, study_flow, study_steps
    from flows.study_config import load_study
    from flows.study_figures import default_report_path, write_study_report

    runner_config = _runner(runner, address, workers, cluster_class, cluster_kwargs)
    config = load_study(preset, overrides)
    command, label = f"study --preset {preset}", f"study {config.name}"
    plan = partial(plan_study, config)
    total = study_steps(config)
    result = _answer_or_run(command, home, plan, total, label, dry_run, study_flow, config, runner_config)
    ws = _workspace(home)
    written = write_study_report(ws, result["report"], report or default_report_path(ws, result["report"]))
    if as_json:
        _print_json({**{k: v for k, v in result.items() if k != "markdown"}, "report_file": str(written)})
        return
    typer.echo(result["markdown"])  # Markdown as written (a console would re-wrap its tables)
    typer.echo(f"study: {result['report']}   (capvector lineage {result['report'][:12]})")
    typer.echo(f"report and figures: {written}")


@app.command()
def calibrate(
    preset: Annotated[str, typer.Option(help="calibrate-control | a YAML path")] = "calibrate-control",
    overrides: SetOption = None,
    home: HomeOption = None,
    as_json: JsonOption = False,
    dry_run: DryRunOption = False,
    runner: RunnerOption = None,
    address: AddressOption = None,
    workers: WorkersOption = 2,
    cluster_class: ClusterClassOption = None,
    cluster_kwargs: ClusterKwargsOption = None,
) -> None:
    """Calibrate a testbed before a study: SFT curves per task on validation goals, the written rule,
    the task sets, and the extraction budget at which held-out loss is flat (or the cap)."""
    if _new_home(home, dry_run):
        _boot_server()
    from functools import partial

    from flows.calibrate import calibrate_flow, calibration_steps, plan_calibration
    from flows.calibrate_config import load_calibration

    runner_config = _runner(runner, address, workers, cluster_class, cluster_kwargs)
    config = load_calibration(preset, overrides)
    command, label = f"calibrate --preset {preset}", f"calibrate {config.name}"
    plan = partial(plan_calibration, config)
    total = calibration_steps(config)
    result = _answer_or_run(command, home, plan, total, label, dry_run, calibrate_flow, config, runner_config)
    if as_json:
        _print_json({k: v for k, v in result.items() if k != "markdown"})
        return
    typer.echo(result["markdown"])  # the preset lines to paste are in it
    typer.echo(f"calibration: {result['calibration']}   (capvector lineage {result['calibration'][:12]})")


@app.command()
def sweep(
    preset: str = "quick",
    overrides: SetOption = None,
    home: HomeOption = None,
    as_json: JsonOption = False,
    runner: RunnerOption = None,
    address: AddressOption = None,
    workers: WorkersOption = 2,
    cluster_class: ClusterClassOption = None,
    cluster_kwargs: ClusterKwargsOption = None,
) -> None:
    """Grid over α and λ for the CapVector arm, picked on validation seeds (never the test seeds)."""
    _boot_server()
    from flows.config import load_config
    from flows.sweep import sweep_flow, sweep_markdown

    runner_config = _runner(runner, address, workers, cluster_class, cluster_kwargs)
    config = load_config(preset, overrides)
    _preflight(f"sweep --preset {preset}", home)
    from flows.runs import run_tags

    with run_tags("sweep", config.name):
        result = _on_runner(sweep_flow, runner_config)(config.model_dump(mode="json"), resolve_home(home))
    if as_json:
        _print_json(result)
    else:
        console.print(sweep_markdown(result))
        console.print(
            f"best: α={result['best']['alpha']} λ={result['best']['lambda']}  (sweep {result['sweep']})"
        )


@app.command()
def schedule(
    cron: Annotated[str, typer.Option(help="cron expression, e.g. '0 3 * * *'")],
    query: Annotated[str | None, typer.Option(help="selection SQL (first column: checkpoint ids)")] = None,
    name: str = "scheduled-reevaluation",
    home: HomeOption = None,
    check: Annotated[bool, typer.Option("--check", help="validate and print, do not serve")] = False,
) -> None:
    """Serve the `reevaluate` deployment on a cron (needs PREFECT_API_URL for a persistent server)."""
    from flows.schedules import build_deployment, serve_deployment

    deployment = build_deployment(cron, resolve_home(home), query, name)
    if check:
        console.print(f"deployment {name!r}: cron {cron!r}, home {resolve_home(home)}")
        return
    serve_deployment(deployment)


# ---------------------------------------------------------------------------- catalogue
@artifacts_app.command("list")
def artifacts_list(
    kind: Annotated[str | None, typer.Option(help="only this kind")] = None,
    limit: int = 50,
    home: HomeOption = None,
    as_json: JsonOption = False,
) -> None:
    """Artifacts in the catalogue, newest first."""
    ws = _workspace(home)
    sql = "SELECT id, kind, name, size_bytes, created_at FROM artifacts"
    params: list[Any] = []
    if kind:
        sql += " WHERE kind = ?"
        params.append(kind)
    columns, rows = ws.api.query_rows(sql + f" ORDER BY created_at DESC LIMIT {int(limit)}", params)
    if as_json:
        _print_json([dict(zip(columns, r, strict=True)) for r in rows])
        return
    table = Table("id", "kind", "name", "size", "created")
    for aid, kind_, name, size, created in rows:
        table.add_row(aid[:12], kind_, name, f"{size:,}", str(created)[:19])
    console.print(table)


@artifacts_app.command("show")
def artifacts_show(artifact_id: str, home: HomeOption = None) -> None:
    """The full record of one artifact (its sidecar: config, parents, versions, runs)."""
    _print_json(_workspace(home).api.get(artifact_id).model_dump(mode="json"))


@app.command()
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
) -> None:
    """Ancestors (default) or descendants of an artifact, with the role of every edge.

    `--kinds`/`--hide` keep some kinds only; a path through the others becomes one edge (its roles
    joined by →), so what is kept stays connected, and `--depth` counts the kept hops."""
    ws = _workspace(home)
    record = ws.api.get(artifact_id)
    filtered = kinds is not None or hide is not None
    rows = (ws.api.descendants if descendants else ws.api.ancestors)(record.id, None if filtered else depth)
    if filtered:
        kept, hidden = ({k.strip() for k in v.split(",") if k.strip()} if v else None for v in (kinds, hide))
        rows = keep_kinds(rows, record, not descendants, kept, hidden, depth)
    if fmt == "json":
        _print_json([r.model_dump() for r in rows])
    elif fmt == "mermaid":
        typer.echo(as_mermaid(rows, record, ancestors=not descendants))
    elif fmt == "tree":
        typer.echo(as_tree(rows, record))
    else:
        raise typer.BadParameter(f"unknown format {fmt!r}; use tree, json or mermaid")


@app.command()
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
    from artifacts.errors import MixedFingerprints
    from flows.protocols import SHOWN, listing, protocols, resolve

    api = _workspace(home).api
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
        _print_json([{**r.model_dump(mode="json"), "protocol": names[r.fingerprint]} for r in rows])
        return
    table = Table("checkpoint", "name", "depth", "task", "success", "episodes", "protocol", "evaluated")
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


@app.command()
def compare(
    checkpoints: Annotated[list[str], typer.Argument(help="checkpoint ids to compare")],
    fingerprint: Annotated[str | None, typer.Option(help="protocol to compare under")] = None,
    plot: Annotated[Path | None, typer.Option(help="write a PNG bar chart here")] = None,
    home: HomeOption = None,
    as_json: JsonOption = False,
) -> None:
    """Latest per-task scores of several checkpoints under one protocol, side by side."""
    from flows.comparison import compare_checkpoints, plot_compare

    ws = _workspace(home)
    result = compare_checkpoints(ws, checkpoints, fingerprint)
    if plot is not None:
        plot_compare(result, plot)
        err.print(f"wrote {plot}")
    if as_json:
        _print_json(result.model_dump(mode="json"))
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


@app.command()
def report(
    report_id: Annotated[
        str | None, typer.Argument(help="a study or report artifact (default: the latest study, else report)")
    ] = None,
    out: Annotated[
        Path | None, typer.Option("-o", "--out", help="Markdown file to write (default: <home>/reports/)")
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
) -> None:
    """Markdown + PNG figures of a study (curves, paired differences, per task) or a pipeline report."""
    from flows.study_figures import default_report_path, latest_study_id, write_study_report

    ws = _workspace(home)
    record = ws.api.get(report_id) if report_id else None
    study_id = record.id if record is not None and record.kind == "study" else None
    if record is None:
        study_id = latest_study_id(ws)
    if study_id is not None:
        path = write_study_report(ws, study_id, out or default_report_path(ws, study_id))
        console.print(f"wrote {path} and its figures")
        return
    from flows.report import latest_report_id, write_report

    sections = {}
    for item in section or []:
        if "=" not in item:
            raise typer.BadParameter(f"--section {item!r} must look like 'TITLE=REPORT_ID'")
        title, rid = item.rsplit("=", 1)
        sections[title] = rid
    rid = record.id if record is not None else latest_report_id(ws)
    target = out or Path(ws.home) / "reports" / f"report-{rid[:12]}.md"
    text = notes.read_text() if notes else None
    path = write_report(ws, rid, target, sections, sweep_id, text)
    console.print(f"wrote {path}")


@app.command()
def sql(query: str, home: HomeOption = None, as_json: JsonOption = False) -> None:
    """Read-only SQL over the catalogue (anything but reading is refused)."""
    columns, rows = _workspace(home).api.query_rows(query)
    if as_json:
        _print_json([dict(zip(columns, r, strict=True)) for r in rows])
    else:
        typer.echo(text_table(columns, rows))


def text_table(columns: list[str], rows: list[tuple]) -> str:
    """Rows as plain aligned text (numbers to the right), whole values: no pandas, no truncation."""
    cells = [["NULL" if v is None else str(v) for v in row] for row in rows]
    numeric = [
        all(isinstance(row[i], int | float) or row[i] is None for row in rows) and bool(rows)
        for i in range(len(columns))
    ]
    widths = [max([len(c), *(len(row[i]) for row in cells)]) for i, c in enumerate(columns)]

    def line(values: list[str]) -> str:
        parts = [v.rjust(w) if num else v.ljust(w) for v, w, num in zip(values, widths, numeric, strict=True)]
        return "  ".join(parts).rstrip()

    return "\n".join([line(list(columns)), *(line(row) for row in cells)])


@app.command("import")
def import_checkpoint(
    path: Path,
    name: Annotated[str | None, typer.Option(help="name in the catalogue")] = None,
    kind: str = "checkpoint",
    home: HomeOption = None,
) -> None:
    """Register an outside safetensors checkpoint (file or sharded directory) in the store."""
    from tasks.vector_commands import import_path

    record = import_path(_workspace(home), path, kind, name)
    console.print(record.id)


# ---------------------------------------------------------------------------- vectors
@vector_app.command("extract")
def vector_extract(
    minuend: Annotated[str, typer.Argument(help="θ_ao: file, sharded dir or artifact id")],
    subtrahend: Annotated[str, typer.Argument(help="θ_ft: file, sharded dir or artifact id")],
    out: Annotated[Path, typer.Option("-o", "--out", help="*.safetensors = one file, else a sharded dir")],
    base: Annotated[str | None, typer.Option(help="θ_pt the vector is meant for")] = None,
    include: Annotated[list[str] | None, typer.Option(help="tensor-name globs to include")] = None,
    exclude: Annotated[list[str] | None, typer.Option(help="tensor-name globs to exclude")] = None,
    home: HomeOption = None,
) -> None:
    """γ = MINUEND − SUBTRAHEND, streamed tensor by tensor; registered in the catalogue."""
    from tasks.vector_commands import extract_cli

    record = extract_cli(_workspace(home), minuend, subtrahend, out, base, include, exclude)
    console.print(f"{out}  (artifact {record.id})")


@vector_app.command("merge")
def vector_merge(
    base: Annotated[str, typer.Argument(help="θ_pt: file, sharded dir or artifact id")],
    vectors: Annotated[list[str], typer.Option("--vector", help="a vector (repeatable)")],
    alphas: Annotated[list[float], typer.Option("--alpha", help="its coefficient (one per --vector)")],
    out: Annotated[Path, typer.Option("-o", "--out", help="*.safetensors = one file, else a sharded dir")],
    include: Annotated[list[str] | None, typer.Option(help="tensor-name globs to merge into")] = None,
    exclude: Annotated[list[str] | None, typer.Option(help="tensor-name globs to keep from base")] = None,
    force: Annotated[bool, typer.Option(help="merge even if a vector names another base")] = False,
    home: HomeOption = None,
) -> None:
    """BASE + Σ α_i·vector_i, streamed; registered in the catalogue with an edge per vector."""
    from tasks.vector_commands import merge_cli

    if len(vectors) != len(alphas):
        raise typer.BadParameter(f"{len(vectors)} --vector but {len(alphas)} --alpha: give one α per vector")
    record = merge_cli(
        _workspace(home), base, list(zip(vectors, alphas, strict=True)), out, include, exclude, force
    )
    console.print(f"{out}  (artifact {record.id})")


@vector_app.command("stats")
def vector_stats(
    vector: Annotated[str, typer.Argument(help="vector: file, sharded dir or artifact id")],
    base: Annotated[str | None, typer.Option(help="θ_pt, for norms relative to the weights")] = None,
    reference: Annotated[str | None, typer.Option(help="a reference vector, e.g. θ_ft − θ_pt")] = None,
    level: Annotated[str, typer.Option(help="tensor | group | all")] = "group",
    home: HomeOption = None,
    as_json: JsonOption = False,
) -> None:
    """Norms, relative norms, cosine and sign agreement per tensor / module group."""
    from tasks.vector_commands import stats_cli

    rows = stats_cli(_workspace(home), vector, base, reference)
    if as_json:
        _print_json([r.model_dump() for r in rows])
        return
    table = Table("name", "numel", "‖γ‖", "‖γ‖/‖θ‖", "cos(ref)", "sign agree")
    for r in rows:
        if r.level != level:
            continue
        table.add_row(
            r.name,
            f"{r.numel:,}",
            f"{r.l2:.4g}",
            _fmt(r.relative_norm),
            _fmt(r.cosine),
            _fmt(r.sign_agreement),
        )
    console.print(table)


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.4g}"


def _descendant_pids(root: int) -> list[int]:
    """Every live process below `root` (from /proc; empty where there is none, e.g. macOS)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, ValueError, IndexError):
            fields = stat.read_text().rsplit(")", 1)[1].split()
            children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, frontier = [], [root]
    while frontier:
        kids = children.get(frontier.pop(), [])
        found += kids
        frontier += kids
    return found


def _stop_descendants() -> None:
    for pid in _descendant_pids(os.getpid()):
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, signal.SIGTERM)


def _stop_on_signals() -> Callable[[], bool]:
    """Ctrl-C (SIGINT) and SIGTERM end the CLI at once and take its helpers along: the step workers
    and Prefect's API server would otherwise outlive it. The workers are stopped first (SIGTERM, then
    their parent-death SIGKILL as the CLI exits), and the CLI exits without flushing anything: every
    step commits atomically, so stopping mid-step loses only that step's unfinished work, exactly as a
    SIGKILL would, and Prefect's pending events (run states, logs for the UI) are dropped with the
    server that would have taken them, instead of being retried for minutes against a stopped one.
    The server is out of the terminal's process group (flows.run_server), so Ctrl-C reaches only the
    CLI and its workers and the CLI says how the run ended: `interrupted`, exit 130 (143 on SIGTERM).

    While a flow runs Prefect swaps in its own SIGTERM handler, which raises inside whatever is
    running; a DuckDB call turns that into "Query interrupted" and the signal is lost. So the signal
    is also recorded below Python's handlers (the wakeup pipe), and the returned `terminated()` tells
    main(). Prefect leaves SIGINT alone."""

    def stop(signum: int, _frame: Any) -> None:
        _end(signum)

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    read_end, write_end = os.pipe()
    os.set_blocking(read_end, False)
    os.set_blocking(write_end, False)
    signal.set_wakeup_fd(write_end, warn_on_full_buffer=False)

    def terminated() -> bool:
        try:
            return int(signal.SIGTERM) in os.read(read_end, 1024)
        except OSError:  # nothing recorded (BlockingIOError)
            return False

    return terminated


def _end(signum: int) -> None:
    """Stop every helper, say `interrupted` on Ctrl-C (terminal and run log), exit 128 + signum."""
    _stop_descendants()
    if signum == signal.SIGINT:
        with contextlib.suppress(OSError):
            os.write(2, b"interrupted\n")
        progress = sys.modules.get("tasks.progress")  # loaded where a run log was started (no import here)
        if progress is not None and (log := os.environ.get(progress.LOG_FILE_ENV)):
            with contextlib.suppress(OSError):
                fd = os.open(log, os.O_WRONLY | os.O_APPEND)
                os.write(fd, f"{time.strftime('%H:%M:%S')} interrupted (Ctrl-C)\n".encode())
                os.close(fd)
    os._exit(128 + signum)


# multiprocessing's resource tracker (a helper process of the step pool) unlinks the pool's semaphores
# when the CLI ends without closing the pool (a signal, kill -9) and warns about them in two lines.
# Nothing is leaked after all; every process it starts gets the interpreter's -W options.
QUIET_RESOURCE_TRACKER = "ignore:resource_tracker:UserWarning:multiprocessing.resource_tracker"


def one_line(exc: BaseException, leave_out: str | None = None) -> str:
    """An error as one line: its message (a pydantic error as `field: problem` per error, DuckDB's
    multi-line messages joined), then its notes (the step it came from) but `leave_out`."""
    from pydantic import ValidationError

    if isinstance(exc, ValidationError):
        parts = []
        for e in exc.errors(include_url=False):
            where = ".".join(str(p) for p in e["loc"]) or exc.title
            got = e.get("input")
            shown = f" (got {got!r})" if isinstance(got, int | float | str) and len(repr(got)) <= 40 else ""
            parts.append(f"{where}: {e['msg']}{shown}")
        text = f"{exc.title}: " + "; ".join(parts)
    else:
        text = str(exc) or type(exc).__name__
    notes = [n for n in getattr(exc, "__notes__", ()) if isinstance(n, str) and n != leave_out]
    return " ".join(line.strip() for part in [text, *notes] for line in part.splitlines() if line.strip())


def _is_duckdb_error(exc: BaseException) -> bool:
    return type(exc).__module__.split(".")[0] in ("duckdb", "_duckdb")


def _is_user_error(exc: BaseException) -> bool:
    """Bad input (exit 2): a bad value, id, path, config or query; anything else exits 1."""
    from pydantic import ValidationError

    user_errors = (ValueError, ArtifactError, ValidationError, FileNotFoundError, FileExistsError)
    # (capvector_core's CheckpointError is a ValueError; not imported: it loads numpy)
    return isinstance(exc, user_errors) or _is_duckdb_error(exc)


STEP_NOTE = "in step "  # tasks.prefect_task notes a step's error as `in step '<label>'`
FIRST_FAILURE_WAIT_S = 5.0


def _failed_step(exc: BaseException) -> tuple[str, BaseException] | None:
    """(step, its error) for the flow's first failed step when `exc` is how a failure reached the CLI:
    that step's error, a later step's, or Prefect's word that a step's inputs never came."""
    steps = sys.modules.get("flows.steps")  # loaded where a flow ran
    if steps is None or not isinstance(exc, Exception):
        return None
    if steps.upstream_failed(exc):  # a step failed: its done-callback may still be on its way
        failure = steps.first_failure(wait_s=FIRST_FAILURE_WAIT_S)
        return (failure.step, failure.error) if failure is not None else None
    step = _step_of(exc)
    if step is None:
        return None
    failure = steps.first_failure()  # one that failed before it, if any
    return (failure.step, failure.error) if failure is not None else (step, exc)


def _step_of(exc: BaseException) -> str | None:
    """The step a step's error names in its note (tasks.prefect_task adds `in step '<label>'`)."""
    import ast

    for note in getattr(exc, "__notes__", ()):
        if isinstance(note, str) and note.startswith(STEP_NOTE):
            with contextlib.suppress(ValueError, SyntaxError):
                label = ast.literal_eval(note.removeprefix(STEP_NOTE))
                if isinstance(label, str):
                    return label
    return None


def _fail(exc: BaseException, code: int, step: str | None = None) -> None:
    """Print the error in one line (after its traceback with --debug) and exit with `code`; a failed
    step's error as `step '<label>' failed: <its message>`."""
    if State.debug:
        import traceback

        traceback.print_exception(exc)
    text = one_line(exc, leave_out=STEP_NOTE + repr(step) if step else None)
    if code == 1:  # not a user error: say what it is and where to look
        text = f"{type(exc).__name__}: {text}" + ("" if State.debug else " (--debug shows the traceback)")
    if step is not None:
        text = f"step {step!r} failed: {text}"
    from rich.markup import escape

    # ids and paths stay whole; a tensor named like rich markup (`x[/bold]`) prints as it is
    err.print(f"[bold red]error:[/] {escape(text)}", soft_wrap=True)
    sys.exit(code)


def main() -> None:
    """Console entry point: an error prints one line naming the problem and exits 2 (bad input) or 1
    (anything else), nothing half-written; `--debug` (or CAPVECTOR_DEBUG=1) shows the traceback. A
    failed flow names the step that failed first and that step's error, whichever error the flow
    raised. Ctrl-C: `interrupted`, exit 130 (see _stop_on_signals)."""
    terminated = _stop_on_signals()
    if QUIET_RESOURCE_TRACKER not in sys.warnoptions:
        sys.warnoptions.append(QUIET_RESOURCE_TRACKER)
    try:
        try:
            code = app(standalone_mode=False)  # click returns a typer.Exit's code here
        except BaseException as exc:
            if terminated():
                _end(signal.SIGTERM)
            failed = _failed_step(exc)
            if failed is not None:
                step, error = failed
                if State.debug and error is not exc:
                    import traceback

                    traceback.print_exception(exc)  # how the flow ended; then the step's own error
                _fail(error, 2 if _is_user_error(error) else 1, step)
            raise
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.Abort:
        sys.exit(130)
    except Exception as exc:
        from typer._click.exceptions import ClickException  # typer vendors click

        if isinstance(exc, ClickException):  # a usage error: click's own message and code
            exc.show()
            sys.exit(exc.exit_code)
        _fail(exc, 2 if _is_user_error(exc) else 1)
    if isinstance(code, int) and code:
        sys.exit(code)


if __name__ == "__main__":
    main()
