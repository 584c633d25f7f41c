"""A study of fine-tuning forms (issue 40's rank study): arm variants with overrides and lr grids, a study
with no γ that runs no extraction stage, and the report's forms table and figure from a real tiny run."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from conftest import run_cli

from capvector.flows.study.config import load_study
from capvector.flows.study.plan import study_plan, study_steps
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.steps.study_analysis import StudyReport

SMOKE = "study-rank-smoke"
R16 = {"arm": "sft_lora", "set": {"lora.r": 16, "lora.alpha": 32}, "lrs": [1.0e-3, 3.0e-3]}


def with_variant(name: str, variant: dict) -> list[str]:
    """An override adding one variant to the smoke preset's (a `--set` replaces the whole mapping)."""
    declared = {k: v.model_dump() for k, v in load_study(SMOKE).study.variants.items()}
    return [f"study.variants={json.dumps({**declared, name: variant})}"]


def labels(plan) -> list[str]:
    return [p.step for p in plan]


def test_a_variant_adds_exactly_its_tuning_runs_selection_seed_runs_and_tests():
    base = load_study(SMOKE)
    with_r16 = load_study(SMOKE, with_variant("lora_r16", R16))
    before, after = labels(study_plan(base)), labels(study_plan(with_r16))
    added = [step for step in after if step not in before]
    assert [step for step in after if step in set(before)] == before  # the rest of the plan is unchanged
    assert all("lora_r16" in step for step in added)
    lrs, tunes, seeds = 2, len(base.study.tuning_seeds), len(base.seeds)
    budgets = len(base.curve_budgets)
    assert len(added) == lrs * tunes * (1 + budgets) + 1 + seeds * (1 + budgets + 1)
    assert sum(step.startswith("tune lora_r16") for step in added) == lrs * tunes
    assert added.count("select lora_r16 lr") == 1
    runs = [p for p in study_plan(with_r16) if p.step.startswith("downstream lora_r16")]
    assert len(runs) == seeds and all(p.config["lora"]["r"] == 16 for p in runs)
    assert all(p.config["lora"]["alpha"] == 32 and p.config["adapter"] == "lora" for p in runs)
    train = runs[0].config["train"]
    assert train["snapshot_steps"] == base.curve_budgets[:-1] and train["lr"] == 1.0e-3  # the first lr
    assert study_steps(with_r16) == (len(after), 0)  # no gate


def test_a_study_without_gamma_runs_no_extraction_stage_and_is_deterministic():
    cfg = load_study(SMOKE)
    assert not cfg.study.needs_gamma
    plan = study_plan(cfg)
    for word in ("extraction", "θ_ft", "θ_ao", "γ", "draw", "merge", "D_ext", "null", "gate"):
        assert not any(word in step for step in labels(plan)), word
    assert [p.config for p in plan] == [p.config for p in study_plan(load_study(SMOKE))]
    gamma = labels(study_plan(load_study("study-smoke", ["study.gate=false"])))
    assert any("θ_ft" in step for step in gamma)  # a study with γ's arms still extracts


def test_a_full_fine_tuning_lr_grid_is_chosen_like_a_variants():
    plan = study_plan(load_study(SMOKE, ["study.sft_lrs=[1.0e-4, 3.0e-4]"]))
    assert sum(step.startswith("tune sft lr=") for step in labels(plan)) == 2
    runs = [p for p in plan if p.step.startswith("downstream sft seed")]
    assert runs and all("selection" in p.inputs for p in runs)
    plain = [p for p in study_plan(load_study(SMOKE)) if p.step.startswith("downstream sft seed")]
    assert all("selection" not in p.inputs for p in plain)


@pytest.mark.parametrize(
    ("variant", "message"),
    [
        (("bad", {"arm": "sft_lora", "set": {"lora.rank": 4}, "lrs": [1e-3]}), r"variants\.bad.*lora\.rank"),
        (("bad", {"arm": "sft_lora", "set": {"lora.r": 0}, "lrs": [1e-3]}), r"variants\.bad.*lora\.r"),
        (("bad", {"arm": "sft_lora", "set": {"lora_sp.bank_size": 4}, "lrs": [1e-3]}), r"bad.*lora_sp"),
        (("bad", {"arm": "sft_lora_sp", "set": {"downstream.steps": 8}, "lrs": [1e-3]}), r"bad.*steps"),
        (("bad", {"arm": "sft_lora", "lrs": [1e-3, 1e-3]}), r"repeated"),
        (("bad", {"arm": "aux", "lrs": [1e-3]}), r"arm"),
        (("Bad", {"arm": "sft_lora", "lrs": [1e-3]}), r"'Bad' must be lower-case"),
        (("aux", {"arm": "sft_lora", "lrs": [1e-3]}), r"named like a study arm"),
    ],
)
def test_bad_variants_are_refused_naming_the_variant(variant, message):
    with pytest.raises(ValueError, match=message):
        load_study(SMOKE, with_variant(*variant))


def test_a_gate_in_a_study_without_gamma_is_refused():
    with pytest.raises(ValueError, match=r"study.gate is true but study.arms \['sft'\] need no γ"):
        load_study(SMOKE, ["study.gate=true"])


@pytest.fixture(scope="module")
def rank_home(tmp_path_factory) -> tuple[Path, dict]:
    home = tmp_path_factory.mktemp("rank-home")
    proc = run_cli("study", "--preset", SMOKE, "--json", home=home)
    return home, json.loads(proc.stdout)


def test_the_rank_report_has_a_row_per_arm_with_its_parameters_and_a_png_figure(rank_home, tmp_path):
    home, ids = rank_home
    ws = Workspace(home)
    report = StudyReport.model_validate(ws.api.store.open_json(ids["report"]))
    variants = list(load_study(SMOKE).study.variants)
    assert set(ids["selections"]) == {f"selection/{v} lr" for v in variants}
    assert set(report.endpoints) == {"sft", *variants} and report.preconditions == []
    assert {s.form for s in report.rank_spread} == {"sft_lora", "sft_lora_sp"}
    for arm in variants:  # adapters are kept and tested at every budget, like full fine-tuning
        assert [p.budget for p in report.curves[arm]] == [0, 8, 16], arm
    out = tmp_path / "rank.md"
    run_cli("report", ids["report"][:12], "-o", str(out), home=home)
    text = out.read_text()
    forms = text.split("## Fine-tuning forms")[1].split("\n## ")[0]
    rows = {line.split(" | ")[0].strip("| "): line for line in forms.splitlines() if line.startswith("| ")}
    for arm in ["sft", *variants]:
        params = rows[arm].split(" | ")[-3]
        assert int(params.replace(",", "")) > 0, rows[arm]
    assert int(rows["lora_r8"].split(" | ")[-3].replace(",", "")) == 4 * int(
        rows["lora_r2"].split(" | ")[-3].replace(",", "")
    )
    assert re.search(r"attn \d", rows["lora_sp_b4"]) and rows["lora_r2"].endswith("| — |")
    assert "Robust to rank" in text
    assert re.search(r"\| lora_sp_b8 − lora_r8 \| [+-]\d+\.\d \[", text)  # a declared comparison
    for figure in ("forms", "capacity", "ranks"):  # vs parameters, vs rank, active ranks per module kind
        assert (out.parent / f"rank_{figure}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", figure
        assert f"(rank_{figure}.png)" in text, figure


def test_ranks_come_from_each_forms_own_override_and_full_fine_tuning_has_none(rank_home):
    from capvector.flows.study.forms_figures import capacity

    home, ids = rank_home
    report = StudyReport.model_validate(Workspace(home).api.store.open_json(ids["report"]))
    ranks = {arm: capacity(report, arm) for arm in ["sft", *report.design.variants]}
    expected = {"lora_r2": 2, "lora_r8": 8, "lora_sp_b4": 4, "lora_sp_b8": 8, "adalora_r2": 2}
    assert ranks == {"sft": None, **expected}


def test_a_lora_sp_snapshot_is_tested_as_init_plus_its_own_adapter(rank_home):
    home, ids = rank_home
    ws = Workspace(home)
    tests = ws.api.query("SELECT parent FROM edges WHERE child = $c AND role = 'test'", {"c": ids["report"]})[
        "parent"
    ]
    forms = {}
    for evaluation in tests:
        record = ws.api.get(evaluation)
        name = ws.api.get(record.parents[0].id).name
        forms[name] = record.config["policy_form"]["form"]
    assert forms["downstream lora_sp_b4 seed 0 @ 8 steps"] == "lora_sp_adapter"
    assert forms["downstream lora_r2 seed 0 @ 8 steps"] == "dense"
