"""The commands that run a flow: run, evaluate, reevaluate, study, calibrate, sweep, schedule.

A planned command first asks the content cache (`_from_cache`): when every step is cached it answers at
once, with no Prefect server, flow run or worker; otherwise the run's server is started and the flow
runs on the runner its options name (capvector.flows.runtime.task_runners). Heavy imports happen inside each
command.
"""

from __future__ import annotations

import os
import re
import shlex
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any

import typer

from capvector.flows.cli.common import (
    DryRunOption,
    HomeOption,
    JsonOption,
    SetOption,
    Table,
    console,
    print_json,
    workspace,
)
from capvector.flows.cli.eval_options import eval_options
from capvector.flows.cli.runner_options import runner_options
from capvector.flows.runtime.home import resolve_home

# Commands that run a flow: they get the run's one Prefect API server
# (capvector.flows.runtime.prefect_server). Its address
# is reserved before Prefect is imported; the process starts when a flow is sure to run.
FLOW_COMMANDS = {"run", "study", "calibrate", "evaluate", "reevaluate", "sweep", "schedule"}


def _boot_server() -> None:
    """Spawn the run's reserved Prefect server now, so that it boots while the command imports torch
    and the flows: for a command sure to run a flow (evaluate, reevaluate; run, study and sweep on a
    new home). Otherwise `preflight` starts it, once the content cache has not answered the plan."""
    from capvector.flows.runtime.prefect_server import start_server_now

    start_server_now()


def _new_home(home: str | None, dry_run: bool) -> bool:
    """A local home that does not exist yet, for a run that is not a dry run: nothing is cached."""
    if dry_run:
        return False
    from capvector.artifacts.home import is_local

    home = resolve_home(home)
    return is_local(home) and not Path(home).exists()


def preflight(command: str, home: str | None) -> None:
    """Before any flow: the run's Prefect server is started (if not yet) and up (a configured but
    unreachable one is an error naming its address, not a hang); progress goes to a log file as well
    as the terminal."""
    from capvector.flows.runtime.prefect_server import wait_for_api
    from capvector.tasks.runtime.prefect_task import quiet_failed_run_logs

    wait_for_api()  # first: an unreachable server must leave no home behind
    _start_log(command, home)
    quiet_failed_run_logs()  # main() prints a failing run's error, in one line


def log_slug(command: str) -> str:
    """A log file's name for `command`: a preset given as a path by its file's stem (`--preset
    /abs/p.yaml` named a file under folders that do not exist), no character a file name should avoid."""
    head, _, preset = command.partition(" --preset ")
    if "/" in preset or preset.endswith((".yaml", ".yml")):
        preset = Path(preset).stem
    slug = "-".join([*head.split(), *([preset] if preset else [])])
    return re.sub(r"[^A-Za-z0-9._-]+", "_", slug).strip("._-")[:80] or "run"


def _start_log(command: str, home: str | None) -> None:
    """Progress to a log file in the home as well as the terminal (step workers inherit the path)."""
    from capvector.tasks.runtime.progress import LOG_FILE_ENV, emit

    if not os.environ.get(LOG_FILE_ENV):
        from datetime import UTC, datetime

        logs = workspace(home).local_root / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
        slug = log_slug(command)
        os.environ[LOG_FILE_ENV] = str(logs / f"{slug}-{stamp}-{os.getpid()}.log")
        from capvector.flows.runtime.housekeeping import prune_on_start

        prune_on_start(resolve_home(home))  # logs stay bounded (~2 ms; the new one is always kept)
    emit(f"capvector {command}: home {resolve_home(home)}, log {os.environ[LOG_FILE_ENV]}")


def _from_cache(
    command: str,
    home: str,
    plan,
    total: int,
    label: str,
    dry_run: bool = False,
    planned: Sequence[str] = (),
    gate_at: int | None = None,
):
    """Know before starting: the plan's result when the content cache answers every step (no Prefect
    run, server wait or worker), else None. `dry_run` prints the plan's cache status and exits: each
    step cached, the first one to run, and (given the recorded plan, `planned`) every step after it.
    `gate_at`: how many of the planned steps come up to and including a gate (the rest run only if it
    passes; they are listed and counted as such). The probe follows the plan's order, so the steps it
    answered are the plan's first ones."""
    from capvector.flows.runtime.step_submission import CacheProbe, NotAllCached

    if _new_home(home, dry_run):
        return None  # a new home caches nothing (and an unreachable server must leave none behind)
    gate_at = total if gate_at is None else gate_at
    probe = CacheProbe(home, gate_at, label)
    try:
        result, missing = plan(probe), None
    except NotAllCached as exc:
        result, missing = None, str(exc)
    if dry_run:
        _print_dry_run(command, probe.answered, missing, list(planned), total, gate_at)
        raise typer.Exit(0)
    if missing is None:
        _start_log(command, home)
        probe.replay()
    return result


def _print_dry_run(
    command: str,
    answered: list[tuple[str, str]],
    missing: str | None,
    planned: list[str],
    total: int,
    gate_at: int,
) -> None:
    """What `--dry-run` prints: the cached steps, then the ones to run, the gated ones marked `gated`,
    and counts of what will run (before the gate, and after it if it passes)."""
    done = len(answered)
    for step, artifact_id in answered:
        typer.echo(f"cached  {artifact_id[:12]}  {step}")
    after = total - gate_at
    if missing is None:
        if done < total and after:
            typer.echo(
                f"all {done} steps up to the gate cached; the gate did not pass, so the {total - done} "
                f"after it do not run: `capvector {command}` prints its result at once"
            )
        else:
            typer.echo(f"all {done} steps cached: `capvector {command}` prints its result at once")
        return
    typer.echo(f"to run  {missing}")
    for i, step in enumerate(planned[done + 1 :], start=done + 1):
        typer.echo(f"{'gated ' if i >= gate_at else 'then  '}  {step}")
    if not after or done >= gate_at:  # no gate, or it passed already: every step left runs
        suffix = " (the gate passed)" if after else ""
        typer.echo(
            f"{total - done} of {total} steps to run or to look up once their inputs exist{suffix} "
            f"(the first: {missing})"
        )
        return
    typer.echo(
        f"{gate_at - done} of {gate_at} steps to run or to look up once their inputs exist before the gate, "
        f"{after} after it if the gate passes (the first: {missing})"
    )


def _answer_or_run(
    command: str,
    home: str | None,
    plan,
    total: int,
    label: str,
    dry_run: bool,
    flow: str,
    config,
    runner_config,
    planned: Sequence[str] = (),
    gate_at: int | None = None,
) -> Any:
    """A planned command's result: from the content cache when it answers every step (no server, no
    flow run, no Prefect import), else from a flow run (server up, log opened, tagged with the command
    and preset). `flow`: the flow as `module:name`, imported only when it has to run."""
    result = _from_cache(command, resolve_home(home), plan, total, label, dry_run, planned, gate_at)
    if result is None:
        from importlib import import_module

        from capvector.flows.runtime.run_records import run_tags

        module, name = flow.split(":")
        flow_fn = getattr(import_module(module), name)
        preflight(command, home)
        with run_tags(command.split()[0], config.name):
            result = _on_runner(flow_fn, runner_config)(config.model_dump(mode="json"), resolve_home(home))
    return result


def _on_runner(flow_fn: Any, config: Any) -> Any:
    from capvector.flows.runtime.task_runners import build_runner

    return flow_fn.with_options(task_runner=build_runner(config))


@runner_options()
def run(
    preset: Annotated[str, typer.Option(help="smoke | quick | paper | path to a YAML file")] = "quick",
    overrides: SetOption = None,
    home: HomeOption = None,
    report: Annotated[
        Path | None,
        typer.Option(
            help="write the Markdown report and its figures here (default: <home>/reports/; "
            "a remote home's local cache folder)"
        ),
    ] = None,
    as_json: JsonOption = False,
    dry_run: DryRunOption = False,
    runner_config: Any = None,  # capvector.flows.runtime.task_runners.RunnerConfig, from the runner options
) -> None:
    """Run the recipe once (cached): demos -> θ_pt -> θ_ft, θ_ao -> γ -> θ_meta -> arms -> tests -> the
    study report. It is the smallest study (one γ draw, the preset's α, λ and learning rates, nothing
    chosen, no gate: flows/study/recipe.py); `--json` adds the ids of what it made."""
    if _new_home(home, dry_run):
        _boot_server()
    from capvector.flows.recipe.config import load_config
    from capvector.flows.study.recipe import recipe_study

    recipe = load_config(preset, overrides)
    config = recipe_study(recipe)
    products = _study_command(f"run --preset {preset}", config, home, report, as_json, dry_run, runner_config)
    if recipe.evaluation.ood_camera is not None and not as_json:
        typer.echo(_ood_hint(recipe, products))


def _ood_hint(recipe: Any, products: dict[str, Any]) -> str:
    """A study tests through its own camera only: the command that tests the run's final checkpoints
    through `evaluation.ood_camera`."""
    camera, data = recipe.evaluation.ood_camera, recipe.data
    finals = " ".join(c[:12] for c in products.get("checkpoints", {}).values())
    tasks, horizon = ",".join(recipe.splits.downstream), recipe.evaluation.horizon
    return (
        f"evaluation.ood_camera {camera}: not tested by the run; to test its final checkpoints through it: "
        f"capvector evaluate {finals} --tasks {tasks} --obs-mode {data.obs_mode} "
        f"--camera {camera} --image-size {data.image_size} --horizon {horizon}"
    )


@runner_options("thread")
@eval_options
def evaluate(
    checkpoints: Annotated[
        list[str],
        typer.Argument(help="checkpoint artifact ids (or unique prefixes), or policy files or folders"),
    ],
    tasks: Annotated[str, typer.Option(help="comma-separated Meta-World task names")],
    home: HomeOption = None,
    as_json: JsonOption = False,
    eval_settings: Any = None,  # EvalConfig's fields, from capvector.flows.cli.eval_options
    runner_config: Any = None,  # capvector.flows.runtime.task_runners.RunnerConfig, from the runner options
) -> None:
    """Evaluate checkpoints on any tasks under one protocol (test seeds, disjoint from demo seeds)."""
    _boot_server()
    from capvector.core.evaluation.rollouts import EvalConfig
    from capvector.flows.evaluation.flow import evaluate_flow

    preflight("evaluate", home)
    config = EvalConfig(tasks=[t.strip() for t in tasks.split(",") if t.strip()], **eval_settings)
    from capvector.tasks.trained_policy import resolve_checkpoints

    checkpoints = resolve_checkpoints(workspace(home), checkpoints)  # paths imported; types checked
    flow_fn = _on_runner(evaluate_flow, runner_config)
    from capvector.flows.runtime.run_records import run_tags

    with run_tags("evaluate"):
        result = flow_fn(resolve_home(home), checkpoints, config.model_dump(mode="json"))
    from capvector.artifacts.scores import read_scores
    from capvector.tasks.steps.evaluation import video_ids_of

    ws = workspace(home)
    scores = {s.evaluation_id: s for s in read_scores(ws.api, evaluations=result.values())}
    videos = video_ids_of(ws, list(result.values()))
    if as_json:
        print_json(
            [
                {"checkpoint": c, "evaluation": e, **scores[e].model_dump(), "videos": _video_rows(videos, e)}
                for c, e in result.items()
            ]
        )
        return
    table = Table("checkpoint", "evaluation", "mean success", "per task")
    for c, e in result.items():
        per_task = ", ".join(f"{t}: {100 * v:.0f}%" for t, v in scores[e].success_rates.items())
        table.add_row(c[:12], e[:12], f"{100 * scores[e].mean_success:.1f}%", per_task)
    console.print(table)
    _print_videos(videos, home)


def _video_rows(videos: dict[str, list[tuple[str, str]]], evaluation: str) -> list[dict[str, str]]:
    return [{"name": name, "id": video} for name, video in videos.get(evaluation, [])]


def _print_videos(videos: dict[str, list[tuple[str, str]]], home: str | None) -> None:
    """Where `evaluate`'s videos are: one line per video artifact, with the command that copies it out
    (every video of the evaluations, also ones an earlier run recorded; GIFs before mp4s)."""
    if not videos:
        return
    home_option = f" --home {shlex.quote(home)}" if home else ""
    typer.echo("videos (evaluation, video name, the command that copies the video here):")
    for evaluation, found in videos.items():
        for name, video in found:
            command = f"capvector artifacts get {video[:12]} -o .{home_option}"
            typer.echo(f"  {evaluation[:12]}  {name}   {command}")


@runner_options("thread")
def reevaluate(
    query: Annotated[
        str | None, typer.Option(help="read-only SQL whose first column is checkpoint ids")
    ] = None,
    home: HomeOption = None,
    as_json: JsonOption = False,
    runner_config: Any = None,  # capvector.flows.runtime.task_runners.RunnerConfig, from the runner options
) -> None:
    """Re-run the evaluations of the selected checkpoints under the installed library versions."""
    _boot_server()
    from capvector.flows.evaluation.flow import DEFAULT_SELECTION, reevaluate_flow, summary_markdown

    preflight("reevaluate", home)
    from capvector.flows.runtime.run_records import run_tags

    with run_tags("reevaluate"):
        changes = _on_runner(reevaluate_flow, runner_config)(resolve_home(home), query or DEFAULT_SELECTION)
    if as_json:
        print_json(changes)
    else:
        console.print(summary_markdown(changes) if changes else "nothing selected")


@runner_options()
def study(
    preset: Annotated[
        str,
        typer.Option(
            help="study-control-hard-extraction-3seeds | study-control-hard-extraction | study-control-small "
            "| study-state | study-pixels | a YAML path"
        ),
    ] = "study-control-hard-extraction-3seeds",
    overrides: SetOption = None,
    home: HomeOption = None,
    report: Annotated[
        Path | None,
        typer.Option(
            help="write the Markdown report and its figures here (default: <home>/reports/; "
            "a remote home's local cache folder)"
        ),
    ] = None,
    as_json: JsonOption = False,
    dry_run: DryRunOption = False,
    runner_config: Any = None,  # capvector.flows.runtime.task_runners.RunnerConfig, from the runner options
) -> None:
    """Run an experiment: selections on validation goals, preconditions, all arms, analysis, report."""
    if _new_home(home, dry_run):
        _boot_server()
    from capvector.flows.study.config import load_study

    config = load_study(preset, overrides)
    _study_command(f"study --preset {preset}", config, home, report, as_json, dry_run, runner_config)


def _study_command(
    command: str,
    config: Any,
    home: str | None,
    report: Path | None,
    as_json: bool,
    dry_run: bool,
    runner: Any,
) -> dict[str, Any]:
    """Plan, answer or run a study (`capvector study`, or `capvector run`'s recipe as one), write its
    report and figures and print it; `--json`: the ids (the report's, the selections', the products').
    Returns the products' ids."""
    from functools import partial

    from capvector.flows.study.figures import default_report_path, write_study_report
    from capvector.flows.study.plan import gated_study_plan, plan_study

    steps, gate_at = gated_study_plan(config)
    planned = [p.step for p in steps]
    flow = "capvector.flows.study.flow:study_flow"
    plan, label = partial(plan_study, config), f"study {config.name}"
    args = (command, home, plan, len(planned), label, dry_run, flow, config, runner, planned, gate_at)
    result = _answer_or_run(*args)
    ws = workspace(home)
    written = write_study_report(ws, result["report"], report or default_report_path(ws, result["report"]))
    products = result.get("products", {})
    if as_json:
        rest = {k: v for k, v in result.items() if k not in ("markdown", "products")}
        print_json({**products, **rest, "report_file": str(written)})
        return products
    typer.echo(result["markdown"])  # Markdown as written (a console would re-wrap its tables)
    typer.echo(f"study: {result['report']}   (capvector lineage {result['report'][:12]})")
    typer.echo(f"report and figures: {written}")
    return products


@runner_options()
def calibrate(
    preset: Annotated[str, typer.Option(help="calibrate-control | a YAML path")] = "calibrate-control",
    overrides: SetOption = None,
    home: HomeOption = None,
    as_json: JsonOption = False,
    dry_run: DryRunOption = False,
    runner_config: Any = None,  # capvector.flows.runtime.task_runners.RunnerConfig, from the runner options
) -> None:
    """Calibrate a testbed before a study: SFT curves per task on validation goals, the written rule,
    the task sets, and the extraction budget at which held-out loss is flat (or the cap)."""
    if _new_home(home, dry_run):
        _boot_server()
    from functools import partial

    from capvector.flows.calibration.config import load_calibration
    from capvector.flows.calibration.plan import calibration_steps, plan_calibration

    config = load_calibration(preset, overrides)
    command, label = f"calibrate --preset {preset}", f"calibrate {config.name}"
    plan = partial(plan_calibration, config)
    total = calibration_steps(config)
    flow = "capvector.flows.calibration.flow:calibrate_flow"
    result = _answer_or_run(command, home, plan, total, label, dry_run, flow, config, runner_config)
    if as_json:
        print_json({k: v for k, v in result.items() if k != "markdown"})
        return
    typer.echo(result["markdown"])  # the preset lines to paste are in it
    typer.echo(f"calibration: {result['calibration']}   (capvector lineage {result['calibration'][:12]})")


@runner_options()
def sweep(
    preset: Annotated[str, typer.Option(help="smoke | quick | paper | path to a YAML file")] = "quick",
    overrides: SetOption = None,
    home: HomeOption = None,
    as_json: JsonOption = False,
    dry_run: DryRunOption = False,
    runner_config: Any = None,  # capvector.flows.runtime.task_runners.RunnerConfig, from the runner options
) -> None:
    """Choose α and λ for `sweep.arm` (capvector) on validation goals (never the test goals): the preset's
    `sweep` grid as a study that ends at its α × λ selection (flows/study/recipe.py), on the γ `run`
    makes (cached where it ran). `--json`: the selection, with its id as `sweep`."""
    if _new_home(home, dry_run):
        _boot_server()
    from functools import partial

    from capvector.flows.recipe.config import lambda_label, load_config
    from capvector.flows.study.plan import plan_study, study_plan
    from capvector.flows.study.recipe import sweep_study

    config = sweep_study(load_config(preset, overrides))
    planned = [p.step for p in study_plan(config)]
    flow = "capvector.flows.study.flow:study_flow"
    plan, label = partial(plan_study, config), f"study {config.name}"
    args = (f"sweep --preset {preset}", home, plan, len(planned), label, dry_run, flow, config, runner_config)
    result = _answer_or_run(*args, planned)
    doc = workspace(home).api.store.open_json(result["sweep"])
    if as_json:
        print_json({"sweep": result["sweep"], **doc})
        return
    typer.echo(result["markdown"])  # Markdown as written (a console would re-wrap its table)
    best = doc["best"]
    typer.echo(f"best: α={best['alpha']} {lambda_label(best)}  (sweep {result['sweep']})")


def schedule(
    cron: Annotated[str, typer.Option(help="cron expression, e.g. '0 3 * * *'")],
    query: Annotated[str | None, typer.Option(help="selection SQL (first column: checkpoint ids)")] = None,
    name: str = "scheduled-reevaluation",
    home: HomeOption = None,
    check: Annotated[bool, typer.Option("--check", help="validate and print, do not serve")] = False,
) -> None:
    """Serve the `reevaluate` deployment on a cron (needs PREFECT_API_URL for a persistent server)."""
    from capvector.flows.evaluation.schedules import build_deployment, serve_deployment

    deployment = build_deployment(cron, resolve_home(home), query, name)
    if check:
        console.print(f"deployment {name!r}: cron {cron!r}, home {resolve_home(home)}")
        return
    serve_deployment(deployment)
