"""The `calibrate` flow: the written rule and the alternating split on hand-made curves, the presets'
sharing of D_pt, θ_pt and D_ext with the study they calibrate, and one tiny real run (Meta-World,
Prefect, the content cache) whose `calibration` artifact holds every curve and verdict, and which a
second run takes whole from the cache."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import settled_task_states

from capvector.artifacts.api import ArtifactsAPI
from capvector.core.simulation.demos import EVAL_SEED_BASE, VALIDATION_SEED_BASE
from capvector.flows.calibration.config import load_calibration
from capvector.flows.calibration.flow import calibrate_flow
from capvector.flows.calibration.plan import calibration_steps, plan_calibration
from capvector.flows.recipe.config import load_config
from capvector.flows.runtime.step_submission import CacheProbe
from capvector.flows.study.config import load_study
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.steps.calibration import (
    TaskRule,
    apply_rule,
    calibration_markdown,
    extraction_convergence,
    ladder,
    split_tasks,
)

RULE = TaskRule(budgets=[50, 100], low=15, high=85, spread=40, min_tasks_per_split=2)


def _curves(per_seed: dict[str, list[tuple[float, float]]]) -> dict:
    """task -> [(success @ 50, success @ 100) per seed] as the flow's curves."""
    return {
        task: {str(s): {"50": a, "100": b} for s, (a, b) in enumerate(points)}
        for task, points in per_seed.items()
    }


# ---------------------------------------------------------------------------- the rule, the split
def test_the_rule_leaves_out_floor_ceiling_and_seed_decided_tasks():
    curves = _curves(
        {
            "floor": [(0, 10), (10, 20)],  # mean 10
            "ceiling": [(90, 100), (80, 90)],  # mean 90
            "spread": [(0, 20), (90, 100)],  # mean 52.5, each seed 42.5 points off
            "kept": [(30, 50), (50, 70)],  # mean 50, each seed 10 off
            "edge": [(15, 15), (15, 15)],  # at the bound: kept
        }
    )
    verdicts = apply_rule(curves, [0, 1], RULE)
    assert {t: v.chosen for t, v in verdicts.items()} == {
        "floor": False,
        "ceiling": False,
        "spread": False,
        "kept": True,
        "edge": True,
    }
    assert verdicts["floor"].reason.startswith("at floor")
    assert verdicts["ceiling"].reason.startswith("at ceiling")
    assert verdicts["spread"].reason.startswith("decided by the seed")
    assert verdicts["spread"].farthest == pytest.approx(42.5)
    assert verdicts["kept"].per_seed == {"0": 40, "1": 60} and verdicts["kept"].mean == 50


def test_the_rule_needs_every_seed_at_every_budget():
    curves = _curves({"t": [(10, 20), (30, 40)]})
    del curves["t"]["1"]["100"]
    with pytest.raises(ValueError, match="seed 1 has no success at budgets \\[100\\]"):
        apply_rule(curves, [0, 1], RULE)


def test_kept_tasks_are_dealt_alternately_down_the_ranking():
    means = {"a": 30, "b": 70, "c": 50, "d": 60, "e": 50, "f": 20, "floor": 5}
    verdicts = apply_rule(_curves({t: [(m, m), (m, m)] for t, m in means.items()}), [0, 1], RULE)
    split = split_tasks(verdicts, min_tasks=3)
    assert split.ranking == ["b", "d", "c", "e", "a", "f"]  # the tie c = e keeps the candidates' order
    assert split.downstream == ["b", "c", "a"] and split.extraction == ["d", "e", "f"]
    assert split.enough and split.shortfall is None


def test_too_few_kept_tasks_are_said_plainly():
    verdicts = apply_rule(
        _curves({t: [(m, m), (m, m)] for t, m in {"a": 50, "b": 40, "c": 99}.items()}), [0, 1], RULE
    )
    split = split_tasks(verdicts, min_tasks=2)
    assert split.downstream == ["a"] and split.extraction == ["b"]
    assert not split.enough
    assert "2 of 3 candidates pass the rule, too few for a study" in split.shortfall
    assert "at least 2 needed in each" in split.shortfall


def test_the_rule_on_the_documented_calibration_gives_study_controls_sets():
    """docs/studies/calibration.md's first calibration (the one study-control's sets were declared from; the
    flow's later measurement follows it) through the rule: study-control's sets, in order."""
    doc = (Path(__file__).resolve().parent.parent / "docs" / "studies" / "calibration.md").read_text()
    first = doc.split("## The calibration as a flow, measured")[0]
    rows = re.findall(r"^\| ([a-z-]+-v3) \| (\d+) \| (\d+) \| (\d+) \| (\d+) \|", first, re.M)
    assert len(rows) == 18
    curves = {
        task: {s: dict(zip(["50", "100", "200", "400"], map(float, cells), strict=True)) for s in ("0", "1")}
        for task, *cells in rows
    }
    rule = TaskRule(budgets=[50, 100, 200, 400])
    split = split_tasks(apply_rule(curves, [0, 1], rule), rule.min_tasks_per_split)
    study = load_study("study-control")
    assert split.enough
    assert split.extraction == study.splits.extraction
    assert split.downstream == study.splits.downstream


def test_extraction_budgets_double_up_to_the_cap_and_stop_at_the_first_flat_run():
    assert ladder(1250, 10000) == [1250, 2500, 5000, 10000]
    assert ladder(1000, 5000) == [1000, 2000, 4000, 5000]
    assert ladder(800, 800) == [800]
    budgets = [100, 200, 400]
    first = extraction_convergence({100: (1.0, 0.8)}, budgets, 0.05)
    assert first.steps is None and first.verdict.startswith("not converged by 100 steps")  # it goes on
    assert extraction_convergence({}, budgets, 0.05).verdict == "not measured"  # too few tasks
    found = extraction_convergence({100: (1.0, 0.8), 200: (0.5, 0.49)}, budgets, 0.05)
    assert found.steps == 200 and [r.flat for r in found.rows] == [False, True]
    assert found.verdict.startswith("converged at 200 steps: held-out loss moved 2.0 %")
    rising = extraction_convergence({100: (1.0, 0.8), 200: (0.5, 0.6), 400: (0.4, 0.3)}, budgets, 0.05)
    assert rising.steps is None and rising.rows[1].relative_drop == pytest.approx(
        -0.2
    )  # overfitting moves too
    assert rising.verdict.startswith("not converged by the cap (400 steps)")
    with pytest.raises(ValueError, match="not a prefix"):
        extraction_convergence({100: (1.0, 1.0), 200: (1.0, 0.5)}, budgets, 0.05)


# ---------------------------------------------------------------------------- the presets
def test_calibrate_control_shares_demos_and_theta_pt_with_study_control():
    calibration, study = load_calibration("calibrate-control"), load_study("study-control")
    pilot = calibration.pilot()
    assert pilot.demo_config("pretrain") == study.demo_config("pretrain")
    assert pilot.pretrain_step() == study.pretrain_step()  # the obs transform included
    train, heldout = calibration.extraction_demos(study.splits.extraction, study.splits.downstream)
    assert train == study.demo_config("extraction") and heldout == study.heldout_demo_config()
    run = calibration.extraction_step(
        study.splits.extraction, study.splits.downstream, study.extraction.steps
    )
    assert run == study.extraction_run(False, 0, study.extraction.lr)
    validation = calibration.validation()
    assert validation.seed_base == VALIDATION_SEED_BASE and validation.tasks == calibration.splits.candidates
    assert calibration.extraction.budgets() == [1250, 2500, 5000, 10000]
    assert len(calibration.splits.candidates) == 18 and calibration.rule.budgets == [50, 100, 200, 400]


def test_calibration_presets_are_checked_before_anything_runs():
    with pytest.raises(ValueError, match="rule.budgets end at 8, downstream.steps is 16"):
        load_calibration("calibrate-smoke", ["rule.budgets=[4, 8]"])
    with pytest.raises(ValueError, match="shares task"):
        load_calibration("calibrate-smoke", ["splits.candidates=[reach-v3, drawer-close-v3]"])
    with pytest.raises(ValueError, match="start_steps"):
        load_calibration("calibrate-smoke", ["extraction.start_steps=32"])
    with pytest.raises(ValueError, match="extraction.steps"):
        load_calibration("calibrate-smoke", ["extraction.steps=100"])
    with pytest.raises(ValueError, match="a study preset, not a calibration: run it with `capvector study"):
        load_calibration("study-smoke")
    with pytest.raises(ValueError, match="a calibration preset, not a study: run it with `capvector calib"):
        load_study("calibrate-smoke")
    with pytest.raises(ValueError, match="is a calibration preset, not a pipeline"):
        load_config("calibrate-smoke")


# ---------------------------------------------------------------------------- a real run

def _artifact_count(home: Path) -> int:
    return int(ArtifactsAPI(str(home)).query("SELECT count(*) AS n FROM artifacts")["n"][0])


def test_a_tiny_calibration_records_every_curve_and_verdict_and_is_then_answered_by_the_cache(tmp_path):
    cfg = load_calibration("calibrate-smoke")
    home = tmp_path / "home"
    state = calibrate_flow(cfg.model_dump(mode="json"), str(home), return_state=True)
    assert state.is_completed(), state
    result = state.result()
    ws = Workspace(str(home))
    record = ws.api.get(result["calibration"])
    assert record.kind == "calibration"
    doc = ws.api.store.open_json(record.id)

    seeds, budgets = [str(s) for s in cfg.seeds], [str(b) for b in cfg.rule.budgets]
    assert set(doc["curves"]) == set(cfg.splits.candidates)
    for task, by_seed in doc["curves"].items():
        assert set(by_seed) == set(seeds), task
        for seed in seeds:
            points = by_seed[seed]  # the store writes JSON keys sorted: "16" before "8"
            assert sorted(points, key=int) == budgets and all(0 <= x <= 100 for x in points.values())
    assert set(doc["verdicts"]) == set(cfg.splits.candidates)
    assert all(v["chosen"] for v in doc["verdicts"].values())  # the smoke rule keeps everything
    assert sorted(doc["split"]["downstream"] + doc["split"]["extraction"]) == sorted(cfg.splits.candidates)
    assert doc["config"]["name"] == "calibrate-smoke" and "text" in doc["rule"]

    # Parents: every pilot evaluation (validation goals only), every extraction run and loss.
    parents = ws.api.query("SELECT parent, role FROM edges WHERE child = $c", {"c": record.id})
    roles = dict(zip(parents["parent"], parents["role"], strict=True))
    evaluations = [p for p, r in roles.items() if r == "validation"]
    assert len(evaluations) == len(seeds) * len(budgets)
    for e in evaluations:
        assert VALIDATION_SEED_BASE <= ws.api.get(e).config["eval"]["seed_base"] < EVAL_SEED_BASE
    rows = doc["extraction"]["rows"]
    assert rows and [r["steps"] for r in rows] == cfg.extraction.budgets()[: len(rows)]
    assert all(not r["flat"] for r in rows[:-1])
    assert doc["extraction"]["steps"] in (None, rows[-1]["steps"])
    assert sum(r == "extraction_run" for r in roles.values()) == len(rows)
    assert sum(r == "held_out_loss" for r in roles.values()) == 2 * len(rows)

    markdown = result["markdown"]
    assert markdown == calibration_markdown(doc)
    for task in cfg.splits.candidates:
        assert f"| {task} |" in markdown
    assert result["preset_lines"][0] == f"splits.extraction=[{', '.join(doc['split']['extraction'])}]"
    assert result["preset_lines"][0] in markdown

    # Again: the CLI's probe answers the whole plan from the cache, and a flow run computes nothing.
    probe = CacheProbe(str(home), calibration_steps(cfg), "calibrate smoke")
    assert plan_calibration(cfg, probe) == result
    assert len(probe.answered) == 3 + len(seeds) * (1 + len(budgets)) + 2 + 3 * len(rows) + 1
    before = _artifact_count(home)
    again = calibrate_flow(cfg.model_dump(mode="json"), str(home), return_state=True)
    assert again.result() == result and _artifact_count(home) == before
    states = settled_task_states(again.state_details.flow_run_id)
    assert states and set(states.values()) == {"Cached"}, states

    # The command: answered from the cache before any flow or server, the same calibration printed.
    cli = subprocess.run(
        [
            sys.executable,
            "-m",
            "capvector.flows.cli.main",
            "--home",
            str(home),
            "calibrate",
            "--preset",
            "calibrate-smoke",
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert cli.returncode == 0, cli.stderr
    assert json.loads(cli.stdout)["calibration"] == result["calibration"]
    assert "every one cached" in cli.stderr + cli.stdout
