"""A flow's step total is `len(plan)`: the flow's own code run against a recorder, so the count
cannot drift from what the flow submits (the study's hand count had, once). Checked here as
properties of the plan; tests/test_study_flow.py checks that a real run announces the total it runs."""

from __future__ import annotations

import pytest

from capvector.flows.recipe.config import load_config
from capvector.flows.study.config import load_study
from capvector.flows.study.plan import gated_study_plan, study_plan, study_steps
from capvector.flows.study.recipe import recipe_study, sweep_study
from capvector.tasks.steps.training import OrthogonalSettings


def labels(plan) -> list[str]:
    return [p.step for p in plan]


def test_the_study_plan_names_each_step_once_and_needs_no_store():
    plan = study_plan(load_study("study-smoke"))
    assert len(set(labels(plan))) == len(plan)
    assert labels(plan)[0].startswith("demos") and labels(plan)[-1].startswith("analyse study")


def test_a_third_draw_adds_exactly_the_steps_that_name_it():
    two = labels(study_plan(load_study("study-smoke", ["study.draws=[0,1]", "study.gate=false"])))
    three = labels(study_plan(load_study("study-smoke", ["study.draws=[0,1,2]", "study.gate=false"])))
    added = [step for step in three if step not in two]
    assert added and all("draw 2" in step for step in added)
    assert [step for step in three if step in set(two)] == two  # the rest of the plan is unchanged


def test_the_gate_adds_its_analysis_and_nothing_else():
    off = labels(study_plan(load_study("study-smoke", ["study.gate=false"])))
    on = labels(study_plan(load_study("study-smoke", ["study.gate=true"])))
    assert sorted(set(on) - set(off)) == ["analyse study study-smoke (gate)"] and set(off) <= set(on)


def test_a_gated_plan_counts_the_steps_before_the_gate_apart_from_those_after_it():
    """Issue 37: the progress total and `--dry-run` count what runs before the gate; the steps after it
    (CapVector's arms, θ_meta, θ_null, the final analysis) are counted apart, as run only if it passes."""
    plan, gate_at = gated_study_plan(load_study("study-smoke", ["study.gate=true"]))
    assert labels(plan)[gate_at - 1] == "analyse study study-smoke (gate)"
    after = labels(plan)[gate_at:]
    assert after[-1] == "analyse study study-smoke"
    assert not any(a in step for step in after for a in ("sft_from_ao", "sft_from_ft", "demos"))
    assert any("capvector" in step for step in after) and any("meta" in step for step in after)
    assert study_steps(load_study("study-smoke", ["study.gate=true"])) == (gate_at, len(plan) - gate_at)
    ungated = load_study("study-smoke", ["study.gate=false"])
    assert study_steps(ungated) == (len(study_plan(ungated)), 0)


def test_a_passed_gate_grows_the_announced_total_to_the_whole_plan(capfd):
    """When the gate passes, the runner's `k/N` total grows by the steps after it, so a study that runs
    every step ends at N/N with N the whole plan."""
    from capvector.flows.runtime.step_submission import PlanRecorder
    from capvector.flows.study.plan import _PlannedStudy, _run_study

    cfg = load_study("study-smoke", ["study.gate=true"])
    before, after = study_steps(cfg)

    class Counted(PlanRecorder):
        label, total = "study study-smoke", before

    recorder = Counted()
    study = _PlannedStudy(cfg, recorder)
    study.gate_more = after
    _run_study(study)  # the recorder's gate passes
    assert recorder.total == before + after == len(recorder.plan)
    assert f"gate passed: {after} more steps, {before + after} in all" in capfd.readouterr().err


@pytest.mark.parametrize("preset", ["smoke", "quick", "hard", "paper", "paper-cpu"])
def test_the_recipe_run_once_is_the_smallest_study_with_the_presets_values(preset):
    """Issue 35: `capvector run` is a study of one γ draw, the preset's seeds, no gate, nothing chosen (no
    tuning run, no selection: α, λ, the lrs and the auxiliary weight as the preset sets them), the final
    budget alone; the adapter forms of CapVector are study arms from θ_meta, those of SFT variants."""
    recipe = load_config(preset)
    cfg = recipe_study(recipe)
    assert (cfg.study.draws, cfg.study.tuning_seeds, cfg.study.gate) == ([recipe.extraction.seed], [], False)
    assert cfg.curve_budgets == [recipe.downstream.steps]
    plan = study_plan(cfg)
    assert not [p.step for p in plan if p.step.startswith(("tune", "select", "validate capvector"))]
    assert labels(plan)[-1] == f"analyse study {recipe.name}" and len(set(labels(plan))) == len(plan)
    by_label = {p.step: p for p in plan}
    assert by_label["draw 0 merge θ_meta"].config["alpha"] == recipe.alpha
    for arm in recipe.arms:
        runs = [p for p in plan if p.step.startswith(f"downstream {arm} ")]
        assert len(runs) == len(recipe.seeds), arm
        want = recipe.downstream_step(arm, recipe.seeds[0])
        got = runs[0].config
        assert (got["adapter"], got["train"]["lr"]) == (want.adapter, want.train.lr), arm
        if want.orthogonal is not None:
            assert got["orthogonal"] == want.orthogonal.model_dump(mode="json"), arm
    design = by_label[f"analyse study {recipe.name}"].config
    assert design["given"] and design["chosen"]["alpha"] == recipe.alpha
    assert design["chosen"]["lambda_absolute"] == recipe.orthogonal.lambda_absolute


@pytest.mark.parametrize("preset", ["smoke", "quick", "hard", "paper", "paper-cpu"])
def test_a_sweep_is_the_runs_gamma_then_its_grid_chosen_by_the_studys_selection_and_nothing_more(preset):
    """Issue 35: `capvector sweep` is a study that ends at its α × λ selection: the run's demos, θ_pt and
    γ (the same steps: cached where `run` ran), then per α a merge and per λ a run at seeds[0] and its
    validation, chosen by the study's own `select α and λ`; no test, held-out loss or analysis."""
    recipe = load_config(preset)
    cfg = sweep_study(recipe)
    plan = study_plan(cfg)
    run = {(p.task, repr(p.config)) for p in study_plan(recipe_study(recipe))}
    lambdas = recipe.sweep.lambda_cells(recipe.orthogonal)
    cells = len(recipe.sweep.alphas) * len(lambdas)
    upstream = [p for p in plan if not p.step.startswith(("tune", "validate", "select"))]
    assert labels(upstream) == [
        "demos pretrain", "demos extraction", "demos downstream", "pretrain θ_pt",
        "draw 0 standard SFT θ_ft", "draw 0 auxiliary SFT θ_ao", "draw 0 capability vector γ",
    ]  # fmt: skip
    assert all((p.task, repr(p.config)) in run for p in upstream)  # the run's own steps
    assert len(plan) == len(upstream) + len(recipe.sweep.alphas) + 2 * cells + 1
    tuned = [p for p in plan if p.step.startswith(f"tune {recipe.sweep.arm} α=")]
    assert {p.config["train"]["seed"] for p in tuned} == {recipe.seeds[0]} and len(tuned) == cells
    assert all(p.config["train"]["steps"] == recipe.downstream.steps for p in tuned)
    (select,) = [p for p in plan if p.task == "select"]
    assert [c["values"] for c in select.config["candidates"]] == [
        {"alpha": a, **lam} for a in recipe.sweep.alphas for lam in lambdas
    ]
    assert select.config["context"] == {"seeds": [recipe.seeds[0]], "endpoint": [recipe.downstream.steps],
                                         "arm": recipe.sweep.arm}  # fmt: skip


def test_a_sweep_of_an_arm_without_the_orthogonal_loss_has_one_cell_per_alpha():
    cfg = sweep_study(load_config("smoke", ["sweep.arm=meta_sft", "sweep.alphas=[0.5, 1.1]"]))
    (select,) = [p for p in study_plan(cfg) if p.task == "select"]
    assert [c["values"] for c in select.config["candidates"]] == [{"alpha": 0.5}, {"alpha": 1.1}]
    sweep = ["study.sweep_arm=capvector", "study.draws=[0]", "study.gate=false"]
    sweep.append("study.extraction_lrs=[1.0e-3]")
    with pytest.raises(ValueError, match=r"study\.extraction_aux_weights must hold one value each, used as"):
        load_study("study-smoke", sweep)
    sweep.append("study.extraction_aux_weights=[0.5]")
    with pytest.raises(ValueError, match=r"a sweep compares nothing .* but study\.arms, study\.aux_weights"):
        load_study("study-smoke", sweep)
    loaded = load_study("study-smoke", [*sweep, "study.arms=[]", "study.aux_weights=[]"])
    assert loaded.study.sweep_arm == "capvector" and loaded.study.needs_gamma


def test_another_seed_adds_a_run_its_test_and_its_held_out_loss_per_arm_to_a_run():
    config = load_config("smoke")
    one = labels(study_plan(recipe_study(config)))
    two = labels(study_plan(recipe_study(config.model_copy(update={"seeds": [*config.seeds, 7]}))))
    added = sorted(step for step in two if step not in one)
    final = config.downstream.steps
    names = {"sft": "sft", "aux": "aux", "capvector": "capvector draw 0"}
    assert added == sorted(
        f"{what} {names[arm]} seed 7{at}"
        for arm in config.arms
        for what, at in (("downstream", ""), ("test", f" @ {final}"), ("held-out loss D_down", ""))
    )


def test_a_study_that_chooses_nothing_takes_one_value_per_grid():
    with pytest.raises(
        ValueError,
        match=r"tuning_seeds is empty \(nothing is chosen\) but .*study\.alphas.* hold several values",
    ):
        load_study("study-smoke", ["study.tuning_seeds=[]", "study.alphas=[0.5, 1.0]"])
    with pytest.raises(ValueError, match="add sft to arms"):
        recipe_study(load_config("smoke", ["arms=[capvector]"]))


def test_a_second_tuning_seed_repeats_every_tuning_run_and_each_selection_averages_both():
    """Issue 41: a value is chosen on the mean over tuning seeds, never on one lucky tuning run."""
    one = study_plan(load_study("study-smoke", ["study.tuning_seeds=[1000]"]))
    two = study_plan(load_study("study-smoke", ["study.tuning_seeds=[1000, 1001]"]))
    tuning = [p.step for p in one if p.step.startswith(("tune ", "tuning "))]
    assert tuning
    for step in tuning:  # each tuning step once per seed
        assert {f"{step} seed 1000", f"{step} seed 1001"} <= set(labels(two)), step
    selections = [p for p in two if p.step.startswith("select ")]
    assert len(selections) == len([p for p in one if p.step.startswith("select ")]) == 4
    for selection in selections:
        assert selection.config["context"]["seeds"] == [1000, 1001]
        cell = selection.config["candidates"][0]["evaluations"]
        single = next(p for p in one if p.step == selection.step).config["candidates"][0]["evaluations"]
        assert len(cell) == 2 * len(single)  # the cell's score averages both seeds' validations


def test_replicates_average_their_draws_and_carry_capvectors_arms():
    """study.draws_per_replicate = 2: each replicate's γ̄ is a mean step over its two draws' γ, and the
    arms that start from a vector (and SFT from θ_ao / θ_ft) run once per replicate, not per draw."""
    cfg = load_study("study-smoke", ["study.draws=[0,1,2,3]", "study.draws_per_replicate=2"])
    plan = study_plan(cfg)
    means = [
        p for p in plan if p.step.startswith("replicate") and p.step.endswith("mean capability vector γ̄")
    ]
    assert [sorted(p.inputs) for p in means] == [["vector 0", "vector 1"]] * 2
    by_label = {p.step: p for p in plan}
    assert [s for s in by_label if s.endswith("null vector")] == [
        "replicate 0 null vector",
        "replicate 1 null vector",
    ]
    for arm in ("capvector", "meta_sft", "null_capvector", "sft_from_ao", "sft_from_ft"):
        runs = [s for s in by_label if s.startswith(f"downstream {arm} ")]
        assert sorted(runs) == [f"downstream {arm} replicate {r} seed {s}" for r in (0, 1) for s in cfg.seeds]
    assert [s for s in by_label if " merge θ_meta" in s and not s.startswith("tune")] == [
        "replicate 0 merge θ_meta",
        "replicate 1 merge θ_meta",
    ]
    with pytest.raises(ValueError, match="split into replicates"):
        load_study("study-smoke", ["study.draws=[0,1,2]", "study.draws_per_replicate=2"])


def test_absolute_lambdas_sit_beside_relative_ones_in_the_grid():
    """Issue 41: λ in the paper's absolute form (1e-4) and as a multiple of ‖∇ loss‖/‖γ‖, in one grid."""
    cfg = load_study(
        "study-smoke",
        [
            "study.lambdas_relative=[0.0, 0.1]",
            "study.lambdas_absolute=[1.0e-4]",
            "study.aux_weights=[0.25, 0.5, 1.0]",
        ],
    )
    plan = study_plan(cfg)
    runs = {p.step: p for p in plan if p.step.startswith("tune capvector")}
    assert sorted(runs) == [
        "tune capvector α=1.0 λ_abs=0.0001",
        "tune capvector α=1.0 λ_rel=0",
        "tune capvector α=1.0 λ_rel=0.1",
    ]
    orthogonal = {s: p.config["orthogonal"] for s, p in runs.items()}
    absolute = orthogonal["tune capvector α=1.0 λ_abs=0.0001"]
    assert (absolute["lambda_absolute"], absolute["lambda_relative"]) == (1.0e-4, None)
    relative = orthogonal["tune capvector α=1.0 λ_rel=0.1"]
    assert (relative["lambda_absolute"], relative["lambda_relative"]) == (None, 0.1)
    grid = next(p for p in plan if p.step == "select α and λ").config["candidates"]
    assert [c["values"] for c in grid] == [
        {"alpha": 1.0, "lambda_relative": 0.0},
        {"alpha": 1.0, "lambda_relative": 0.1},
        {"alpha": 1.0, "lambda_absolute": 1.0e-4},
    ]
    with pytest.raises(ValueError, match="aux_weights has 2 values, the α × λ grid 3 cells"):
        load_study("study-smoke", ["study.lambdas_absolute=[1.0e-4]"])


def test_a_study_without_a_lambda_grid_tunes_the_one_lambda_its_preset_sets():
    """Both study grids empty: the `orthogonal` section's λ, in the form it is set, is the grid's only λ."""
    for orthogonal, want in (
        ("orthogonal.lambda_relative=0.3", {"lambda_relative": 0.3}),
        ("orthogonal.lambda_absolute=0.002", {"lambda_absolute": 0.002}),
    ):
        cfg = load_study("study-smoke", ["study.lambdas_relative=[]", "study.aux_weights=[0.25]", orthogonal])
        grid = next(p for p in study_plan(cfg) if p.step == "select α and λ").config["candidates"]
        assert [c["values"] for c in grid] == [{"alpha": 1.0, **want}]


def test_lambda_takes_one_form_and_the_old_names_say_what_they_became():
    with pytest.raises(ValueError, match="lambda_absolute and orthogonal.lambda_relative are both set"):
        OrthogonalSettings.model_validate({"lambda_absolute": 0.1, "lambda_relative": 0.1})
    with pytest.raises(ValueError, match="orthogonal.weight was renamed: set lambda_absolute"):
        OrthogonalSettings.model_validate({"weight": 0.1})  # a preset written before the rename
    with pytest.raises(ValueError, match="'orthogonal.scale' was renamed: set lambda_absolute .* lambda_rel"):
        load_config("smoke", ["orthogonal.scale=absolute"])
    with pytest.raises(ValueError, match="'study.lambda_scales' was renamed: .* as lambdas_relative"):
        load_study("study-smoke", ["study.lambda_scales=[0.1]"])
    with pytest.raises(ValueError, match="'sweep.lambdas' was renamed: .* as lambdas_absolute"):
        load_config("smoke", ["sweep.lambdas=[0.1]"])
    relative = load_config("smoke", ["orthogonal.lambda_relative=0.5"]).downstream_step("capvector", 0)
    assert relative.orthogonal.lam == {"lambda_relative": 0.5}  # the paper's default gives way


def test_a_dose_arm_and_a_tuning_mean_vector_change_only_what_they_name():
    """study.dose_alpha with arm meta_sft_dose: one more merge per unit at the dose α and its runs;
    study.tuning_vector_draws: the α × λ runs of every tuning seed share one γ̄_tune (the mean of those
    draws, which no compared arm uses) and one merge per α."""
    arms = "study.arms=[sft,aux,sft_from_ao,sft_from_ft,meta_sft,meta_sft_dose,capvector,null_capvector]"
    base = ["study.tuning_seeds=[1000,1001]"]
    plain = study_plan(load_study("study-smoke", base))
    cfg = load_study(
        "study-smoke", [*base, arms, "study.dose_alpha=2.0", "study.tuning_vector_draws=[100,101,102]"]
    )
    plan = study_plan(cfg)
    by_label = {p.step: p for p in plan}
    (mean,) = [p for p in plan if p.step == "tuning mean capability vector γ̄_tune"]
    assert sorted(mean.inputs) == ["vector 0", "vector 1", "vector 2"]
    assert [s for s in by_label if s.startswith("draw 10") and s.endswith("capability vector γ")] == [
        f"draw {d} capability vector γ" for d in (100, 101, 102)
    ]
    assert not any(s.startswith("validate draw 10") for s in by_label)  # tuning draws are not compared
    tune_merges = [s for s in by_label if s.startswith("tune merge")]
    assert tune_merges == ["tune merge θ_meta α=1.0"]  # one per α, shared by both tuning seeds
    assert "tuning capability vector γ seed 1000" in labels(plain) and not any(
        s.startswith("tuning capability vector") for s in by_label
    )
    dose = [p for p in plan if p.step.endswith("merge θ_meta α=2.0")]
    assert [p.step for p in dose] == [f"draw {d} merge θ_meta α=2.0" for d in cfg.study.draws]
    assert all(p.config["alpha"] == 2.0 for p in dose)
    runs = [s for s in by_label if s.startswith("downstream meta_sft_dose ")]
    want = [f"downstream meta_sft_dose draw {d} seed {s}" for d in cfg.study.draws for s in cfg.seeds]
    assert sorted(runs) == sorted(want)
    with pytest.raises(ValueError, match="dose_alpha and the arm meta_sft_dose"):
        load_study("study-smoke", ["study.dose_alpha=2.0"])
    with pytest.raises(ValueError, match="tuning_vector_draws"):
        load_study("study-smoke", ["study.tuning_vector_draws=[0, 100]"])


def test_a_lambda_cell_reads_the_same_in_every_report_including_sweeps_recorded_before_the_rename():
    from capvector.flows.recipe.config import lambda_label

    assert lambda_label({"alpha": 1.1, "lambda_relative": 0.1}) == "λ_rel=0.1"
    assert lambda_label({"alpha": 1.1, "lambda_absolute": 1e-4}) == "λ_abs=0.0001"
    assert lambda_label({"alpha": 1.1, "lambda": 1e-4}) == "λ_abs=0.0001"  # an old sweep
    assert lambda_label({"alpha": 1.1}) == "λ none"


def test_a_sweep_recorded_by_the_old_sweep_flow_still_renders_beside_one_a_sweep_study_records():
    """`capvector report --sweep` reads both: the sweep flow's selection (`seed`, an absolute `lambda`)
    and a sweep study's (`seeds`, the λ forms' names)."""
    from capvector.flows.recipe.report import _sweep_seed
    from capvector.flows.study.report import sweep_markdown

    cells = [{"alpha": a, "lambda": 1e-4, "validation_success": v} for a, v in ((0.5, 0.25), (1.1, 0.5))]
    old = {"arm": "capvector", "seed": 0, "grid": cells, "best": cells[1]}
    cell = {"alpha": 1.1, "lambda_relative": 0.1, "validation_success": 1.0}
    new = {"arm": "capvector", "seeds": [0], "grid": [cell], "best": cell}
    assert sweep_markdown(old).splitlines()[2:] == [
        "| 0.5 | λ_abs=0.0001 | 25.0% |", "| 1.1 | λ_abs=0.0001 | 50.0% **(best)** |"
    ]  # fmt: skip
    assert sweep_markdown(new).splitlines()[2:] == ["| 1.1 | λ_rel=0.1 | 100.0% **(best)** |"]
    assert (_sweep_seed(old), _sweep_seed(new)) == (0, "0")


GATE_ONLY = ["study.gate=true", "study.arms=[sft,aux,sft_from_ao,sft_from_ft]"]


def test_a_gate_only_study_is_the_gated_plan_up_to_its_gate_and_needs_no_capvector_arm():
    """Issue 39's powered gate: a study of the preconditions alone plans exactly the steps a full study
    runs before its gate (same labels, same order) and nothing after it."""
    full_plan, gate_at = gated_study_plan(load_study("study-smoke", ["study.gate=true"]))
    gate_only = load_study("study-smoke", GATE_ONLY)
    assert gate_only.study.gate_only
    plan = study_plan(gate_only)
    assert labels(plan) == labels(full_plan)[:gate_at]
    assert labels(plan)[-1] == "analyse study study-smoke (gate)"
    assert study_steps(gate_only) == (len(plan), 0)


def test_without_the_gate_the_gate_arms_alone_are_refused_naming_the_missing_arm():
    with pytest.raises(ValueError, match=r"must include \['capvector'\].*gate-only study lists exactly"):
        load_study("study-smoke", ["study.gate=false", "study.arms=[sft,aux,sft_from_ao,sft_from_ft]"])


def test_a_gate_only_report_says_the_gate_passed_and_that_capvector_was_not_part_of_it():
    from capvector.flows.study.report import _gate
    from capvector.tasks.steps.study_analysis import StudyDesign, StudyReport

    def report(stage: str) -> StudyReport:
        design = StudyDesign.model_construct(stage=stage, endpoint_budgets=[10, 20], final_budget=20)
        return StudyReport.model_construct(gate=None, design=design, comparisons=[], designs_for_5_points={})

    text = "\n".join(_gate(report("gate")))
    assert "declared gate-only" in text
    assert "| (c′) | SFT from θ_ao − SFT | — | **not settled** |" in text  # nothing compared: nothing read
    assert _gate(report("final")) == []
