"""The `study` flow end to end on the tiny preset, through the real CLI: selections are artifacts with
their validation evaluations as parents, every compared run uses them and is tested on the same goals at
every budget, the controls are what they claim, the report holds preconditions and comparisons, and a
second run is answered by the cache."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from safetensors.numpy import load_file

from capvector.core.simulation.demos import EVAL_SEED_BASE, UNIT_SEEDS, VALIDATION_SEED_BASE
from capvector.flows.study.config import load_study
from capvector.stats.paired_differences import ENDPOINT
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.steps.study_analysis import StudyReport
from tests.conftest import run_cli
from tests.golden_report import GOLDEN, golden_differences, same_numbers


@pytest.fixture(scope="module")
def study_home(tmp_path_factory) -> tuple[Path, dict]:
    home = tmp_path_factory.mktemp("study-home")
    proc = run_cli("study", "--preset", "study-smoke", "--json", home=home)
    return home, json.loads(proc.stdout)


def _parents(ws: Workspace, artifact_id: str) -> list[tuple[str, str]]:
    rows = ws.api.query(
        "SELECT parent, role FROM edges WHERE child = $c ORDER BY role, parent", {"c": artifact_id}
    )
    return list(rows.itertuples(index=False, name=None))


def test_selections_come_from_validation_goals_and_are_parents_of_what_uses_them(study_home):
    home, ids = study_home
    ws = Workspace(home)
    assert set(ids["selections"]) == {
        "selection/extraction lr",
        "selection/extraction auxiliary weight",
        "selection/auxiliary weight",
        "selection/α and λ",
    }
    report = StudyReport.model_validate(ws.api.store.open_json(ids["report"]))
    for selection in ids["selections"].values():
        evaluations = [p for p, role in _parents(ws, selection) if role == "validation"]
        assert len(evaluations) >= 2
        for e in evaluations:
            seeds = ws.api.get(e).config["eval"]
            assert VALIDATION_SEED_BASE <= seeds["seed_base"] < EVAL_SEED_BASE  # never a test goal
    grid = ids["selections"]["selection/α and λ"]
    for arm in ("capvector", "null_capvector", "meta_sft"):
        for checkpoint in report.final_checkpoints[arm]:
            assert (grid, "selected_by") in _parents(ws, checkpoint), arm
    aux = ids["selections"]["selection/auxiliary weight"]
    assert all((aux, "selected_by") in _parents(ws, c) for c in report.final_checkpoints["aux"])
    assert not any(
        role == "selected_by" for c in report.final_checkpoints["sft"] for _, role in _parents(ws, c)
    )


def test_every_run_is_tested_on_the_same_goals_at_every_budget(study_home):
    home, ids = study_home
    ws = Workspace(home)
    report = StudyReport.model_validate(ws.api.store.open_json(ids["report"]))
    config = load_study("study-smoke")
    tests = [p for p, role in _parents(ws, ids["report"]) if role == "test"]
    draws, seeds = len(config.study.draws), len(config.seeds)
    runs = 2 * seeds + 5 * draws * seeds  # sft, aux shared; five arms per draw
    starts = 1 + 4 * draws  # budget 0: θ_pt; each draw's θ_meta, θ_null, θ_ao, θ_ft
    assert len(tests) == runs * len(config.curve_budgets) + starts
    assert len({ws.api.get(t).config["protocol"]["seeds"].__repr__() for t in tests}) == 1
    for arm, points in report.curves.items():
        assert [p.budget for p in points] == [0, *config.curve_budgets], arm
    names = [ws.api.get(c).name for ids_ in report.final_checkpoints.values() for c in ids_]
    assert len(set(names)) == len(names)  # a checkpoint's name carries its draw
    kept = ws.api.get(report.final_checkpoints["capvector"][0]).config
    assert set(kept["snapshots"]) == {str(b) for b in config.curve_budgets[:-1]}
    summary = kept["summary"]
    assert summary["gradient_ratio"] > 0
    chosen = report.design.chosen["lambda_relative"]
    assert summary["lambda_relative"] == chosen
    assert summary["lambda_absolute"] == pytest.approx(chosen * summary["gradient_ratio"])


def test_the_null_vector_has_gammas_norms_and_is_merged_and_regularized_like_it(study_home):
    home, ids = study_home
    ws = Workspace(home)
    report = StudyReport.model_validate(ws.api.store.open_json(ids["report"]))
    checkpoint = report.final_checkpoints["null_capvector"][0]
    parents = dict((role, p) for p, role in _parents(ws, checkpoint))
    null = parents["regularized_by"]
    (gamma,) = [p for p, role in _parents(ws, null) if role == "norms_from"]
    assert ws.api.get(gamma).kind == "vector" and ws.api.get(null).kind == "vector"
    a, b = load_file(str(ws.path(gamma))), load_file(str(ws.path(null)))
    for name in a:
        np.testing.assert_allclose(np.linalg.norm(b[name]), np.linalg.norm(a[name]), rtol=1e-4)
    merged = dict((role, p) for p, role in _parents(ws, parents["init"]))
    assert merged["vector"] == null  # θ_null = θ_pt + α·γ_null


def test_the_report_states_preconditions_comparisons_and_the_design(study_home):
    home, ids = study_home
    ws = Workspace(home)
    report = StudyReport.model_validate(ws.api.store.open_json(ids["report"]))
    assert [p.key for p in report.preconditions] == ["a", "b", "c", "c_prime", "d", "e"]
    assert report.gate is None and not report.design.gate  # study-smoke runs every arm
    assert len(report.convergence) == 2 * len(report.design.draws)  # θ_ft and θ_ao per draw
    pairs = {(c.arm, c.baseline, c.budget) for c in report.comparisons}
    for baseline in ("sft", "aux", "meta_sft", "null_capvector"):
        for budget in (ENDPOINT, report.design.final_budget):
            assert ("capvector", baseline, budget) in pairs
    for c in report.comparisons:
        assert -100 <= c.ci_low <= c.difference <= c.ci_high <= 100
        assert c.n_goals == report.goals_per_task * len(report.tasks)


def test_the_study_report_has_figures_and_no_interval_outside_its_range(study_home, tmp_path):
    home, ids = study_home
    default = sorted((home / "reports").glob("study-smoke-*.md"))  # `study` wrote it into the home
    assert default and default[0].read_text().startswith("# Study `study-smoke`")
    out = tmp_path / "report" / "smoke.md"
    proc = run_cli("report", ids["report"][:12], "-o", str(out), home=home)
    assert "wrote" in proc.stdout
    text = out.read_text()
    figures = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    assert len(figures) >= 2 and "smoke_losses.png" in figures  # training loss per arm, from the records
    for name in figures:
        assert (out.parent / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for low, high in re.findall(r"\[([+-]?\d+\.\d), ([+-]?\d+\.\d)\]", text):
        assert -100 <= float(low) <= float(high) <= 100, (low, high)
    assert "(e)" in text and "endpoint" in text
    latest = run_cli("report", "-o", str(tmp_path / "latest.md"), home=home)  # the latest study
    assert "wrote" in latest.stdout and (tmp_path / "latest.md").exists()


def _progress_lines(home: Path) -> list[str]:
    """The newest study log's `[study study-smoke k/N] step: done|cached` lines."""
    log = max((home / "logs").glob("study-*.log"), key=lambda p: p.stat().st_mtime)
    return [
        line
        for line in log.read_text().splitlines()
        if "] " in line and line.rstrip().endswith(("done", "cached"))
    ]


def test_a_second_run_is_answered_by_the_cache(study_home):
    home, ids = study_home
    again = json.loads(run_cli("study", "--preset", "study-smoke", "--json", home=home).stdout)
    assert again["report"] == ids["report"]
    lines = _progress_lines(home)
    assert lines and all(line.endswith("cached") for line in lines)
    counts = [re.search(r"\[study study-smoke (\d+)/(\d+)\]", line) for line in lines]
    assert [int(m.group(1)) for m in counts] == list(range(1, len(lines) + 1))
    assert {int(m.group(2)) for m in counts} == {len(lines)}  # the announced total is what ran


def test_a_gate_that_fails_stops_the_study_and_says_why(study_home):
    """On the same home with the gate on: everything before the gate is cached; tiny runs show no
    benefit from the auxiliary objective, so the report says the question is untestable and CapVector's
    arms are never trained. The dry run's count before the gate is the number of steps the gated run
    then runs (issue 37: it said "all 269 steps cached" of a study that ran 151), and its progress
    counts to that number."""
    home, ids = study_home
    gate = ("study", "--preset", "study-smoke", "--set", "study.gate=true")
    dry = run_cli(*gate, "--dry-run", home=home).stdout
    counted = re.search(r"(\d+) of (\d+) steps to run .* before the gate, (\d+) after it if the gate", dry)
    assert counted, dry
    before, after = int(counted.group(2)), int(counted.group(3))
    assert int(counted.group(1)) == 1  # only the gate's analysis is new on this home
    assert dry.count("\ngated ") == after and "to run  analyse study study-smoke (gate)" in dry
    gated = json.loads(run_cli(*gate, "--json", home=home).stdout)
    lines = _progress_lines(home)
    counts = [re.search(r"\[study study-smoke (\d+)/(\d+)\]", line) for line in lines]
    assert len(lines) == before and {int(m.group(2)) for m in counts} == {before}
    again = run_cli(*gate, "--dry-run", home=home).stdout
    assert f"all {before} steps up to the gate cached; the gate did not pass, so the {after} after" in again
    ws = Workspace(home)
    report = StudyReport.model_validate(ws.api.store.open_json(gated["report"]))
    assert report.design.stage == "gate" and "untestable" in report.gate
    assert not next(p for p in report.preconditions if p.key == "d").measured  # θ_meta never merged
    assert set(report.final_checkpoints) <= {"sft", "aux", "sft_from_ao", "sft_from_ft"}
    assert "α and λ" not in " ".join(gated["selections"])
    assert "Gate: the question is untestable here" in Path(gated["report_file"]).read_text()


def test_study_presets_are_checked_before_anything_runs(tmp_path):
    with pytest.raises(ValueError, match="aux_weights"):
        load_study("study-smoke", ["study.aux_weights=[0.5]"])
    with pytest.raises(ValueError, match="budgets"):
        load_study("study-smoke", ["study.budgets=[16]"])
    with pytest.raises(ValueError, match="draws"):
        load_study("study-smoke", ["study.draws=[-1, 0]"])  # -1 marks the shared arms
    with pytest.raises(ValueError, match="study.gate needs arms"):
        load_study("study-smoke", ["study.gate=true", "study.arms=[sft, capvector]"])
    with pytest.raises(ValueError, match=r"tuning_seeds \[0\] are also compared"):
        load_study("study-smoke", ["study.tuning_seeds=[1000, 0]"])
    with pytest.raises(ValueError, match="lambdas_relative.0"):
        load_study("study-smoke", ["study.lambdas_relative=[-0.1, 1.0]"])
    with pytest.raises(ValueError, match="not a study"):
        load_study("smoke")
    proc = run_cli("run", "--preset", "study-smoke", home=tmp_path / "home", check=False)
    assert proc.returncode != 0 and "capvector study --preset study-smoke" in proc.stderr


def test_the_hard_extraction_presets_are_study_control_small_with_their_declared_changes():
    """`make run`'s study and the one that answers issue 26 differ from `study-control-small` only where
    their comments say: study-control-hard's split swapped (its six hardest tasks train θ_ft and θ_ao),
    the larger policy, 3 draws; the answer adds 8 seeds and 30 test goals per task."""
    base, hard = load_study("study-control-small"), load_study("study-control-hard")
    small = load_study("study-control-hard-extraction-small")
    answer = load_study("study-control-hard-extraction")
    assert small.splits.extraction == hard.splits.downstream
    assert small.splits.downstream == hard.splits.extraction
    expected = base.model_copy(
        update={
            "name": small.name,
            "splits": small.splits,
            "policy": base.policy.model_copy(update={"d_model": 128, "n_layers": 4}),
            "study": base.study.model_copy(update={"draws": [0, 1, 2]}),
        }
    )
    assert small.model_dump() == expected.model_dump()
    expected = small.model_copy(
        update={
            "name": answer.name,
            "seeds": list(range(8)),
            "evaluation": small.evaluation.model_copy(update={"episodes_per_task": 30}),
        }
    )
    assert answer.model_dump() == expected.model_dump()


def test_the_pixels_study_records_patch_targets_where_its_objective_reads_them():
    config = load_study("study-pixels")
    assert config.aux.name == "spatial_depth"
    assert not config.demo_config("pretrain").patch_xyz
    for split in ("extraction", "downstream"):
        demo = config.demo_config(split)
        assert demo.patch_xyz and demo.patch_grid == config.policy.grid_size
    assert config.heldout_demo_config().seed_offset >= config.demo_config("extraction").n_units * UNIT_SEEDS
    assert config.evaluation.episodes_per_task * len(config.splits.downstream) >= 250


def test_the_report_numbers_are_the_golden_ones(study_home):
    """Refactors keep behaviour: every number of study-smoke's report (curves, comparisons,
    preconditions, held-out losses, designs) equals the committed one. The golden file was written at
    this test's commit and is identical to the numbers of d27eac8, 32 commits before it, whose flows had
    hand-counted totals, string-labelled inputs and statistics inside tasks/. Ids are left out: they
    embed code hashes. After an intended change of results, rewrite the file from a run
    (tests/golden_report.py `report_numbers(report)`) and say why."""
    home, ids = study_home
    report = StudyReport.model_validate(Workspace(home).api.store.open_json(ids["report"]))
    golden = json.loads(GOLDEN.read_text())
    assert any(c["difference"] for c in golden["heldout_loss"])  # the file holds numbers that can move
    differences = golden_differences(report)
    assert not differences, "\n".join(differences[:20])


def test_the_golden_comparison_can_fail():
    golden = json.loads(GOLDEN.read_text())
    moved = json.loads(GOLDEN.read_text())
    moved["heldout_loss"][0]["arm_mean"] *= 1.001
    assert same_numbers(moved, golden) == [
        f"/heldout_loss[0]/arm_mean: {moved['heldout_loss'][0]['arm_mean']!r}, "
        f"golden {golden['heldout_loss'][0]['arm_mean']!r}"
    ]
    assert same_numbers(golden, golden) == []
