"""The `pipeline` flow end to end on the smoke preset: caching, partial re-runs, lineage, resume."""

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
from conftest import REPO, run_cli, settled_task_states

from capvector.artifacts.api import ArtifactsAPI
from capvector.artifacts.scores import read_scores
from capvector.core.simulation.demos import VALIDATION_SEED_BASE
from capvector.flows.recipe.config import load_config
from capvector.flows.recipe.flow import pipeline
from capvector.flows.recipe.report import write_report
from capvector.flows.recipe.sweep import sweep_flow
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.steps import reporting

UPSTREAM = ("pretrained", "standard", "auxiliary", "vector", "meta")


def _artifact_count(home) -> int:
    return int(ArtifactsAPI(str(home)).query("SELECT count(*) AS n FROM artifacts")["n"][0])


def _run(home, overrides=()):
    config = load_config("smoke", list(overrides)).model_dump(mode="json")
    state = pipeline(config, str(home), return_state=True)
    assert state.is_completed(), state
    return state.result(), settled_task_states(state.state_details.flow_run_id)


def test_cold_run_produces_every_artifact(smoke_home):
    home, ids = smoke_home
    api = ArtifactsAPI(str(home))
    cold_run = "SELECT flow_run_id FROM runs WHERE flow_name = 'pipeline' ORDER BY started_at LIMIT 1"
    kinds = dict(
        api.query(
            f"SELECT kind, count(*) AS n FROM artifacts WHERE flow_run_id = ({cold_run}) GROUP BY kind"
        ).values.tolist()
    )
    assert kinds["dataset"] == 3
    assert kinds["checkpoint"] == 3 + 1 + 3  # θ_pt, θ_ft, θ_ao; θ_meta; three downstream arms
    assert kinds["vector"] == 1 and kinds["vector_stats"] == 1
    assert kinds["evaluation"] == 3 and kinds["report"] == 1
    report = api.store.open_json(ids["report"])
    assert set(report["arms"]) == {"sft", "aux", "capvector"}
    episodes = api.query(
        "SELECT count(*) AS n FROM eval_episodes WHERE evaluation_id IN (?, ?, ?)",
        list(ids["evaluations"].values()),
    )
    assert episodes["n"][0] == 3 * 2  # arms × episodes


def test_progress_of_the_run_and_of_each_long_step_is_in_the_log_file(smoke_home):
    """The CLI's log file (also written with CAPVECTOR_QUIET, as here) has the pipeline's step k of N
    and the step workers' demo, training and evaluation lines."""
    home, _ = smoke_home
    logs = sorted((home / "logs").glob("run*.log"))
    assert logs, f"no run log in {home / 'logs'}"
    text = logs[0].read_text()
    finished = [line for line in text.splitlines() if "[pipeline smoke " in line and "/15]" in line]
    assert len(finished) == 15 and all(line.endswith(": done") for line in finished), text
    for long_step in ("[demos pretrain] 4/4 episodes", "[pretrain θ_pt] 30/30 steps, loss ",
                      "[evaluate sft/seed0] 2/2 episodes"):  # fmt: skip
        assert long_step in text, f"{long_step!r} missing from the run log:\n{text}"


def test_second_run_hits_every_cache_and_creates_nothing(smoke_home):
    home, ids = smoke_home
    before = _artifact_count(home)
    again, states = _run(home)
    assert again == ids
    assert _artifact_count(home) == before
    assert states and set(states.values()) == {"Cached"}, states


def test_lineage_of_capvector_checkpoint_reaches_demos_through_the_vector(smoke_home):
    home, ids = smoke_home
    rows = ArtifactsAPI(str(home)).ancestors(ids["checkpoints"]["capvector/seed0"])
    by_id = {r.id: r for r in rows}
    for key in UPSTREAM:
        assert ids[key] in by_id, key
    assert by_id[ids["meta"]].roles == ["init"]
    assert "minuend" in by_id[ids["auxiliary"]].roles and "subtrahend" in by_id[ids["standard"]].roles
    assert set(ids["datasets"].values()) <= set(by_id)
    vectors = ArtifactsAPI(str(home)).vectors_merged_into(ids["checkpoints"]["capvector/seed0"])
    assert [(v.vector_id, v.alpha) for v in vectors] == [(ids["vector"], 1.1)]


def test_changing_a_downstream_setting_reruns_only_the_steps_below(smoke_home):
    home, ids = smoke_home
    changed, states = _run(home, ["downstream.steps=24"])
    assert changed["datasets"] == ids["datasets"]
    for key in UPSTREAM:
        assert changed[key] == ids[key], key
    assert set(changed["checkpoints"].values()).isdisjoint(ids["checkpoints"].values())
    ran = {name for name, state in states.items() if state != "Cached"}
    assert ran and all(n.startswith(("downstream", "evaluate", "report")) for n in ran), ran
    # task-run names spell Greek letters in ASCII (the Prefect UI's graph drops them)
    assert {n for n, s in states.items() if s == "Cached"} >= {"pretrain theta_pt", "capability vector gamma"}


def test_a_cache_hit_whose_artifact_vanished_recomputes_it(smoke_home):
    home, ids = smoke_home
    api = ArtifactsAPI(str(home))
    shutil.rmtree(api.store.object_path(ids["vector"]), ignore_errors=True)
    if os.path.exists(api.store.object_path(ids["vector"])):
        os.remove(api.store.object_path(ids["vector"]))
    again, states = _run(home)
    assert states["capability vector gamma"] == "Completed"
    assert states["pretrain theta_pt"] == "Cached"
    assert again["vector"] == ids["vector"]  # same inputs, same bytes, same id
    api.path(ids["vector"], verify=True)  # restored and intact


def test_a_killed_flow_resumes_from_cached_steps(smoke_home, tmp_path):
    _, reference = smoke_home
    home = tmp_path / "home"
    env = {**os.environ, "CAPVECTOR_HOME": str(home), "CAPVECTOR_QUIET": "1"}
    cmd = [sys.executable, "-m", "capvector", "run", "--preset", "smoke", "--json"]
    proc = subprocess.Popen(
        cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, start_new_session=True
    )
    index = home / "step-cache"
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        if index.exists() and len(list(index.glob("*.json"))) >= 5:  # demos ×3, θ_pt, one more
            break
        time.sleep(0.2)
    if proc.poll() is not None:
        pytest.fail("the run finished before it could be killed")
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()

    resumed = json.loads(run_cli("run", "--preset", "smoke", "--json", home=home).stdout)
    assert resumed["datasets"] == reference["datasets"]
    for key in ("pretrained", "standard", "auxiliary", "meta"):
        assert resumed[key] == reference[key], (key, resumed, reference)
    assert resumed["checkpoints"] == reference["checkpoints"], (resumed, reference)

    frame = ArtifactsAPI(str(home)).query("SELECT kind, count(*) AS n FROM artifacts GROUP BY kind")
    assert dict(frame.values.tolist()) == {
        "dataset": 3,
        "checkpoint": 7,
        "vector": 1,
        "vector_stats": 1,
        "evaluation": 3,
        "report": 1,
    }


def test_pixels_run_tests_the_same_checkpoints_through_the_ood_camera(tmp_path):
    overrides = [
        "data.obs_mode=pixels", "policy.obs_mode=pixels", "data.image_size=32", "policy.image_size=32",
        "arms=[sft]", "evaluation.ood_camera=corner3",
    ]  # fmt: skip
    config = load_config("smoke", overrides).model_dump(mode="json")
    state = pipeline(config, str(tmp_path / "home"), return_state=True)
    assert state.is_completed(), state
    ids = state.result()
    api = ArtifactsAPI(str(tmp_path / "home"))
    main, ood = (api.store.open_json(ids[k]) for k in ("report", "ood_report"))
    assert main["fingerprint"] != ood["fingerprint"]
    main_run, ood_run = main["arms"]["sft"]["runs"][0], ood["arms"]["sft"]["runs"][0]
    assert main_run["checkpoint_id"] == ood_run["checkpoint_id"] == ids["checkpoints"]["sft/seed0"]
    cameras = {api.get(r["evaluation_id"]).config["protocol"]["camera"] for r in (main_run, ood_run)}
    assert cameras == {"corner2", "corner3"}
    summary = api.get(main_run["checkpoint_id"]).config["summary"]
    wall = summary["steps"] / summary["steps_per_s"]
    # measured times are provenance: in the checkpoint's record, not in the report's content (its id)
    workspace = Workspace(str(tmp_path / "home"))
    assert reporting.timings(workspace, reporting.Report.model_validate(main))["sft"]["train_wall_s"] == (
        pytest.approx(wall)
    )
    lr = config["downstream"]["lr"]
    assert f"| {summary['trainable_parameters']} | {lr:g} | 1 |" in main["markdown"]
    text = write_report(workspace, ids["report"], tmp_path / "report.md").read_text()
    assert f"| {wall:.0f} | {summary['trainable_parameters']} | {lr:g} | 1 |" in text


def test_sweep_picks_alpha_and_lambda_on_validation_seeds_and_shares_the_pipeline_steps(smoke_home, tmp_path):
    home, ids = smoke_home
    config = load_config("smoke", ["sweep.alphas=[0.5, 1.1]", "sweep.lambdas_absolute=[1.0e-4]"])
    result = sweep_flow(config.model_dump(mode="json"), str(home))
    api = ArtifactsAPI(str(home))
    assert [(row["alpha"], row["lambda_absolute"]) for row in result["grid"]] == [(0.5, 1e-4), (1.1, 1e-4)]
    assert result["best"] == max(result["grid"], key=lambda row: row["validation_success"])
    for row in result["grid"]:
        (evaluation_id,) = row["evaluation_ids"]  # one budget: the sweep judges the final one
        evaluation = api.get(evaluation_id).config
        assert evaluation["eval"]["seed_base"] == VALIDATION_SEED_BASE  # never the test seeds
        (scores,) = read_scores(api, evaluations=[evaluation_id])
        assert scores.mean_success == row["validation_success"]
    # α = 1.1, λ = 1e-4 is the preset's own CapVector arm: the sweep reuses the pipeline's checkpoint
    assert result["grid"][1]["checkpoint_ids"] == [ids["checkpoints"]["capvector/seed0"]]
    assert result["grid"][0]["checkpoint_ids"][0] not in ids["checkpoints"].values()
    assert api.get(result["sweep"]).kind == "selection"

    one_cell = load_config("smoke", ["sweep.alphas=[1.1]", "sweep.lambdas_absolute=[1.0e-4]"]).model_dump(
        mode="json"
    )
    one_cell = sweep_flow(one_cell, str(home))
    assert one_cell["grid"] == result["grid"][1:]  # every step cached
    sweeps = [result["sweep"], one_cell["sweep"], result["sweep"]]
    text = write_report(Workspace(str(home)), ids["report"], tmp_path / "r.md", sweep_ids=sweeps).read_text()
    grid = f"## α × λ sweep `{result['sweep'][:12]}` (validation goal variations, arm `capvector`, seed 0"
    assert text.count(f"{grid}, lr {config.downstream.lr:g})") == 1  # a repeated id is shown once
    # the one-cell sweep (how an lr is chosen) is a row of the learning-rate table, not a grid of its own
    assert f"## α × λ sweep `{one_cell['sweep'][:12]}`" not in text
    cell = one_cell["grid"][0]
    success = f"{100 * cell['validation_success']:.1f}% **(best)**"
    lr = f"{config.downstream.lr:g}"
    assert f"| capvector | {lr} | 1.1 | λ_abs=0.0001 | {success} | 0 | `{one_cell['sweep'][:12]}` |" in text
