"""`capvector run` end to end on the smoke preset: the recipe run once, as the smallest study (one γ draw,
nothing chosen, no gate; capvector.flows.study.recipe) on the study flow: caching, partial re-runs,
lineage, resume; the α × λ sweep beside it, a study too (on the run's γ, ending at its selection)."""

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
from capvector.flows.study.flow import study_flow
from capvector.flows.study.recipe import recipe_study, sweep_study

UPSTREAM = ("pretrained", "standard", "auxiliary", "vector", "meta")
KINDS = {  # 5 demo sets (3 + 2 held out); θ_pt, θ_ft, θ_ao (each kept at 10 and 15 steps too), θ_meta,
    # θ_null, three arms; γ and γ_null; 9 tests and D_ext validations; 9 held-out losses; the study
    "dataset": 5,
    "checkpoint": 12,
    "vector": 2,
    "vector_stats": 1,
    "evaluation": 9,
    "measurement": 9,
    "study": 1,
}
STEPS = 34


def _artifact_count(home) -> int:
    return int(ArtifactsAPI(str(home)).query("SELECT count(*) AS n FROM artifacts")["n"][0])


def _ids(result: dict) -> dict:
    """What `capvector run --json` prints, from the flow's result (the report file aside)."""
    return {**result["products"], "report": result["report"], "selections": result["selections"]}


def _run(home, overrides=()):
    config = recipe_study(load_config("smoke", list(overrides))).model_dump(mode="json")
    state = study_flow(config, str(home), return_state=True)
    assert state.is_completed(), state
    return _ids(state.result()), settled_task_states(state.state_details.flow_run_id)


def test_cold_run_produces_every_artifact(smoke_home):
    home, ids = smoke_home
    api = ArtifactsAPI(str(home))
    cold_run = "SELECT flow_run_id FROM runs WHERE flow_name = 'study' ORDER BY started_at LIMIT 1"
    kinds = dict(
        api.query(
            f"SELECT kind, count(*) AS n FROM artifacts WHERE flow_run_id = ({cold_run}) GROUP BY kind"
        ).values.tolist()
    )
    assert kinds == KINDS
    study = api.store.open_json(ids["report"])
    assert api.get(ids["report"]).kind == "study"
    assert study["design"]["given"] and study["design"]["draws"] == [0] and study["selections"] == {}
    assert set(ids["checkpoints"]) == set(ids["evaluations"]) == {"sft/seed0", "aux/seed0", "capvector/seed0"}
    episodes = api.query(
        "SELECT count(*) AS n FROM eval_episodes WHERE evaluation_id IN (?, ?, ?)",
        list(ids["evaluations"].values()),
    )
    assert episodes["n"][0] == 3 * 2  # arms × episodes
    assert (home / "reports").is_dir() and ids["report_file"].endswith(".md")


def test_progress_of_the_run_and_of_each_long_step_is_in_the_log_file(smoke_home):
    """The CLI's log file (also written with CAPVECTOR_QUIET, as here) has the study's step k of N
    and the step workers' demo, training and evaluation lines."""
    home, _ = smoke_home
    logs = sorted((home / "logs").glob("run*.log"))
    assert logs, f"no run log in {home / 'logs'}"
    text = logs[0].read_text()
    finished = [line for line in text.splitlines() if "[study smoke " in line and f"/{STEPS}]" in line]
    assert len(finished) == STEPS and all(line.endswith(": done") for line in finished), text
    for long_step in ("[demos pretrain] 4/4 episodes", "[pretrain θ_pt] 30/30 steps, loss ",
                      "[test sft seed 0 @ 20] 2/2 episodes"):  # fmt: skip
        assert long_step in text, f"{long_step!r} missing from the run log:\n{text}"


def test_second_run_hits_every_cache_and_creates_nothing(smoke_home):
    home, ids = smoke_home
    before = _artifact_count(home)
    again, states = _run(home)
    assert again == {k: v for k, v in ids.items() if k != "report_file"}
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
    assert {ids["datasets"][k] for k in ("pretrain", "extraction", "downstream")} <= set(by_id)
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
    assert ran and all(
        n.startswith(("downstream", "test", "held-out loss D_down", "analyse")) for n in ran
    ), ran
    # task-run names spell Greek letters in ASCII (the Prefect UI's graph drops them)
    cached = {n for n, s in states.items() if s == "Cached"}
    assert cached >= {"pretrain theta_pt", "draw 0 capability vector gamma"}


def test_a_cache_hit_whose_artifact_vanished_recomputes_it(smoke_home):
    home, ids = smoke_home
    api = ArtifactsAPI(str(home))
    shutil.rmtree(api.store.object_path(ids["vector"]), ignore_errors=True)
    if os.path.exists(api.store.object_path(ids["vector"])):
        os.remove(api.store.object_path(ids["vector"]))
    again, states = _run(home)
    assert states["draw 0 capability vector gamma"] == "Completed"
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
        if index.exists() and len(list(index.glob("*.json"))) >= 7:  # demos ×5, θ_pt, one more
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
    assert dict(frame.values.tolist()) == KINDS


def test_a_pixels_run_says_how_to_test_its_checkpoints_through_the_ood_camera():
    """A study tests through its own camera: `capvector run` prints the `capvector evaluate` command that
    tests its final checkpoints through `evaluation.ood_camera`, with the run's protocol."""
    from capvector.flows.cli.experiment_commands import _ood_hint

    overrides = [
        "data.obs_mode=pixels", "policy.obs_mode=pixels", "data.image_size=32", "policy.image_size=32",
        "evaluation.ood_camera=corner3",
    ]  # fmt: skip
    recipe = load_config("smoke", overrides)
    hint = _ood_hint(recipe, {"checkpoints": {"sft/seed0": "a" * 64, "capvector/seed0": "b" * 64}})
    assert hint.endswith(
        f"capvector evaluate {'a' * 12} {'b' * 12} --tasks button-press-topdown-v3 --obs-mode pixels "
        "--camera corner3 --image-size 32 --horizon 40"
    )


def _sweep(home, overrides=()):
    """`capvector sweep`'s flow: the preset's α × λ sweep as a study (capvector.flows.study.recipe)."""
    config = sweep_study(load_config("smoke", list(overrides))).model_dump(mode="json")
    state = study_flow(config, str(home), return_state=True)
    assert state.is_completed(), state
    return state.result(), settled_task_states(state.state_details.flow_run_id)


def test_sweep_is_a_study_on_the_runs_gamma_that_picks_alpha_and_lambda_on_validation_goals(smoke_home):
    home, ids = smoke_home
    result, states = _sweep(home, ["sweep.alphas=[0.5, 1.1]", "sweep.lambdas_absolute=[1.0e-4]"])
    # the run's demos, θ_pt, θ_ft, θ_ao and γ: the same steps, answered by the cache
    for step in ("pretrain theta_pt", "draw 0 standard SFT theta_ft", "draw 0 auxiliary SFT theta_ao",
                 "draw 0 capability vector gamma"):  # fmt: skip
        assert states[step] == "Cached", (step, states)
    for key in ("pretrained", "standard", "auxiliary", "vector"):
        assert result["products"][key] == ids[key], key
    assert result["products"]["datasets"] == {k: ids["datasets"][k] for k in result["products"]["datasets"]}
    assert not any(name.startswith(("test", "analyse", "held-out")) for name in states), states  # it ends
    api = ArtifactsAPI(str(home))
    doc = api.store.open_json(result["sweep"])
    assert api.get(result["sweep"]).kind == "selection"
    assert list(result["selections"].values()) == [result["sweep"]]
    assert [(row["alpha"], row["lambda_absolute"]) for row in doc["grid"]] == [(0.5, 1e-4), (1.1, 1e-4)]
    assert doc["best"] == max(doc["grid"], key=lambda row: row["validation_success"])
    assert doc["arm"] == "capvector" and doc["seeds"] == [0]  # the preset's first seed
    for row in doc["grid"]:
        (evaluation_id,) = row["evaluation_ids"]  # no budgets: the sweep judges the final checkpoint
        evaluation = api.get(evaluation_id).config
        assert evaluation["eval"]["seed_base"] == VALIDATION_SEED_BASE  # never the test seeds
        (scores,) = read_scores(api, evaluations=[evaluation_id])
        assert scores.mean_success == row["validation_success"]
    # the cell at the preset's own α and λ is the run's CapVector arm (the same steps, cached)
    assert doc["grid"][1]["checkpoint_ids"] == [ids["checkpoints"]["capvector/seed0"]]

    one_cell, _ = _sweep(home, ["sweep.alphas=[1.1]", "sweep.lambdas_absolute=[1.0e-4]"])
    assert api.store.open_json(one_cell["sweep"])["grid"] == doc["grid"][1:]  # every training step cached

    # `capvector sweep` on the smoke preset (this grid): the cache answers it; the table, the best α, λ
    best = doc["best"]
    out = run_cli("sweep", "--preset", "smoke", home=home).stdout
    assert f"best: α={best['alpha']} λ_abs=0.0001  (sweep {result['sweep']})" in out, out
    assert out.count("**(best)**") == 1 and "| α | λ | validation success |" in out
    as_json = json.loads(run_cli("sweep", "--preset", "smoke", "--json", home=home).stdout)
    assert as_json == {"sweep": result["sweep"], **doc}
