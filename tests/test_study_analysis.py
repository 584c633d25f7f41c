"""The study's analysis on synthetic evaluations with known effects: comparisons find them, the
preconditions' verdicts follow the evidence, and a one-draw study is analysed rather than crashing."""

from __future__ import annotations

import numpy as np
import pytest

from capvector.stats.paired_differences import ENDPOINT
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.steps.held_out_loss import MEASUREMENT_KIND
from capvector.tasks.steps.study_analysis import StudyDesign, analyse, gate_passed, run_analyse_study
from capvector.tasks.study_inputs import (
    CapabilityVector,
    DownstreamLoss,
    ExtractionValidation,
    HeldOutLoss,
    StandardRun,
    TestEvaluation,
)

TASKS = ("reach-v3", "push-v3")
GOALS = 40
TRUE_P = {"sft": 0.3, "capvector": 0.7, "sft_from_ao": 0.5, "sft_from_ft": 0.5}


def _evaluation(ws: Workspace, name: str, p: float, rng: np.random.Generator) -> str:
    checkpoint = ws.api.register_json({"w": name}, "checkpoint", name).id
    episodes = [
        {"task": t, "seed": 100_000 + g, "success": bool(rng.random() < p), "steps": 5, "return": 0.0}
        for t in TASKS
        for g in range(GOALS)
    ]
    return ws.api.register_evaluation(
        {"checkpoint_id": checkpoint, "fingerprint": "f" * 64, "episodes": episodes}, name=name
    ).id


def _loss(ws: Workspace, name: str, value: float, merged: float | None = None) -> str:
    doc = {"action_loss": value} if merged is None else {"action_loss": value, "merged_action_loss": merged}
    return ws.api.register_json(doc, MEASUREMENT_KIND, name).id


def _study(ws: Workspace, draws: list[int], seeds: list[int]) -> tuple[dict[str, str], StudyDesign]:
    rng = np.random.default_rng(0)
    inputs = {}
    for arm, p in TRUE_P.items():
        for d in [-1] if arm == "sft" else draws:
            for s in seeds:
                for b in (10, 20):
                    inputs[TestEvaluation(arm=arm, draw=d, seed=s, budget=b).key] = _evaluation(
                        ws, f"{arm} {d} {s} {b}", p, rng
                    )
    inputs[ExtractionValidation(which="pt", draw=-1).key] = _evaluation(ws, "pt", 0.9, rng)
    for d in draws:
        inputs[ExtractionValidation(which="ft", draw=d).key] = _evaluation(ws, f"ft {d}", 0.2, rng)
        inputs[ExtractionValidation(which="ao", draw=d).key] = _evaluation(
            ws, f"ao {d}", 0.8, rng
        )  # (b): clearly better
        inputs[ExtractionValidation(which="meta", draw=d).key] = _evaluation(
            ws, f"meta {d}", 0.3, rng
        )  # (d): clearly worse
        for run, curve in (
            ("standard", (1.0, 0.99, 0.985)),
            ("auxiliary", (1.0, 0.8, 0.6)),
        ):  # (a): ao still falls
            for b, v in zip((50, 75, 100), curve, strict=True):
                inputs[HeldOutLoss(which=run, draw=d, budget=b).key] = _loss(ws, f"{run} {d} {b}", v)
    design = StudyDesign(
        name="synthetic",
        arms=list(TRUE_P),
        draws=draws,
        seeds=seeds,
        endpoint_budgets=[10, 20],
        final_budget=20,
        extraction_steps=100,
        flat_tolerance=0.05,
        non_inferiority_margin=5.0,
        n_boot=300,
        chosen={"extraction_lr": 1e-3, "aux_weight": 1.0, "alpha": 1.0, "lambda_relative": 0.1},
        grids={
            "extraction_lr": [1e-4, 1e-3],
            "aux_weight": [1.0],
            "alpha": [0.5, 1.0, 2.0],
            "lambda_relative": [0.1],
        },
    )
    return inputs, design


def test_known_effects_are_found_and_preconditions_follow_the_evidence(tmp_path):
    ws = Workspace(tmp_path / "home")
    inputs, design = _study(ws, draws=[0, 1, 2], seeds=[0, 1, 2])  # (b), (d): one run per draw, 2 df
    report = analyse(ws, inputs, design)
    main = next(
        c for c in report.comparisons if (c.arm, c.baseline, c.budget) == ("capvector", "sft", ENDPOINT)
    )
    assert main.ci_low > 0 and main.difference == pytest.approx(40, abs=10)
    upper = next(
        c
        for c in report.comparisons
        if (c.arm, c.baseline, c.budget) == ("sft_from_ao", "sft_from_ft", ENDPOINT)
    )
    assert upper.ci_low < upper.difference < upper.ci_high
    verdicts = {p.key: p.holds for p in report.preconditions}
    assert verdicts["a"] is False  # θ_ao's held-out loss still fell 40 % over the second half
    assert verdicts["b"] is True
    assert verdicts["c"] is not True  # no true difference
    assert verdicts["c_prime"] is True  # SFT from θ_ao 0.5 against SFT 0.3
    assert verdicts["d"] is False
    assert report.goals_per_task == GOALS and report.tasks == sorted(TASKS)
    assert design.at_edge() == []  # 1.0 is inside [0.5, 2]; two-value grids have no inside
    assert "capvector-sft" in report.designs_for_5_points


def test_a_one_draw_study_is_analysed(tmp_path):
    ws = Workspace(tmp_path / "home")
    inputs, design = _study(ws, draws=[0], seeds=[0, 1])
    report = analyse(ws, inputs, design.model_copy(update={"draws": [0], "seeds": [0, 1]}))
    main = next(
        c for c in report.comparisons if (c.arm, c.baseline, c.budget) == ("capvector", "sft", ENDPOINT)
    )
    assert main.n_draws == 1 and main.unestimated  # what one draw cannot separate is named


def test_the_gate_stops_a_study_whose_benefit_does_not_transfer(tmp_path):
    """(b) holds but (c) is not shown: the gate-stage report says why the question is untestable, and
    the flow's check (`gate_passed`) reads it from the stored artifact."""
    ws = Workspace(tmp_path / "home")
    inputs, design = _study(ws, draws=[0, 1, 2], seeds=[0, 1, 2])
    gate = design.model_copy(update={"stage": "gate"})
    report_id = run_analyse_study(ws, "analyse (gate)", inputs, gate.model_dump(mode="json"))
    assert not gate_passed(ws, report_id)
    report = analyse(ws, inputs, gate)
    assert "untestable" in report.gate and "(c)" in report.gate and "(b)" not in report.gate
    assert "(c′)" not in report.gate  # (c′) holds here: only (c) stops it
    assert analyse(ws, inputs, design).gate is None  # the final stage never gates


def test_the_endpoint_is_each_goals_mean_over_the_budgets(tmp_path):
    """An arm that fails at the early budget and succeeds at the final one scores 50 at the endpoint;
    the curve keeps both budgets."""
    ws = Workspace(tmp_path / "home")
    rng = np.random.default_rng(0)
    inputs = {}
    for s in (0, 1):
        for b, p in ((10, 0.0), (20, 1.0)):
            inputs[TestEvaluation(arm="capvector", draw=0, seed=s, budget=b).key] = _evaluation(
                ws, f"c {s} {b}", p, rng
            )
            inputs[TestEvaluation(arm="sft", draw=-1, seed=s, budget=b).key] = _evaluation(
                ws, f"s {s} {b}", 0.0, rng
            )
    _, design = _study(Workspace(tmp_path / "other"), draws=[0], seeds=[0, 1])
    design = design.model_copy(update={"arms": ["sft", "capvector"], "draws": [0]})
    report = analyse(ws, inputs, design)
    main = next(
        c for c in report.comparisons if (c.arm, c.baseline, c.budget) == ("capvector", "sft", ENDPOINT)
    )
    assert main.arm_mean == pytest.approx(50.0) and main.baseline_mean == 0.0
    assert [p.budget for p in report.curves["capvector"]] == [10, 20]
    with pytest.raises(ValueError, match="lacks test episodes at some of the endpoint's budgets"):
        analyse(ws, inputs, design.model_copy(update={"endpoint_budgets": [10, 20, 30]}))


def _tensors_file(ws: Workspace, tmp_path, name: str, tensors: dict, kind: str) -> str:
    from safetensors.torch import save_file

    path = tmp_path / f"{name}.safetensors"
    save_file(tensors, str(path))
    return ws.api.register_file(path, kind, name).id


def test_precondition_e_estimates_the_signal_fraction_and_norm_with_intervals(tmp_path):
    """γ^d = s + noise^d with a known signal fraction ρ: ρ̂ (mean pairwise cosine) and ‖ŝ‖ (from the
    pairwise dot products) find it, with jackknife intervals over draws; replicate means agree as ρ̂
    predicts; cos(γ, θ_ft − θ_pt) is reported."""
    import torch

    from capvector.tasks.steps.vectors import run_mean_vector
    from capvector.tasks.study_inputs import Pretrained, ReplicateVector

    ws = Workspace(tmp_path / "home")
    inputs, design = _study(ws, draws=[0, 1, 2, 3], seeds=[0, 1])
    g = torch.Generator().manual_seed(0)
    n, rho = 200_000, 0.25
    signal = torch.randn(n, generator=g) * rho**0.5
    vectors = {}
    for d in range(4):
        gamma = {"w": signal + torch.randn(n, generator=g) * (1 - rho) ** 0.5}
        vectors[d] = _tensors_file(ws, tmp_path, f"gamma{d}", gamma, "vector")
        inputs[CapabilityVector(draw=d).key] = vectors[d]
        ft = {"w": gamma["w"] * 0.5 + torch.randn(n, generator=g)}
        inputs[StandardRun(draw=d).key] = _tensors_file(ws, tmp_path, f"ft{d}", ft, "checkpoint")
    inputs[Pretrained().key] = _tensors_file(ws, tmp_path, "pt", {"w": torch.zeros(n)}, "checkpoint")
    for r in range(2):
        pair = {f"vector {i}": vectors[2 * r + i] for i in range(2)}
        inputs[ReplicateVector(replicate=r).key] = run_mean_vector(ws, f"replicate {r}", pair, {})
    e = next(p for p in analyse(ws, inputs, design).preconditions if p.key == "e")
    v = e.detail_values
    assert v["rho"] == pytest.approx(rho, abs=0.01)
    assert v["rho_low"] < v["rho"] < v["rho_high"] and v["rho_low"] > 0 and e.holds is True
    assert v["signal_norm"] == pytest.approx((rho * n) ** 0.5, rel=0.03)
    assert v["signal_norm_low"] <= v["signal_norm"] <= v["signal_norm_high"]
    assert v["replicate_cos"] == pytest.approx(v["replicate_cos_predicted"], abs=0.03)  # 2ρ/(1+ρ) = 0.4
    assert v["cos_ft_reference"] > 0.3  # θ_ft − θ_pt carries half of γ here
    assert "ρ̂ 0.2" in e.detail and "replicates of 2 draws" in e.detail
    noise_only = {
        d: _tensors_file(ws, tmp_path, f"noise{d}", {"w": torch.randn(n, generator=g)}, "vector")
        for d in range(4)
    }
    for d, vector in noise_only.items():
        inputs[CapabilityVector(draw=d).key] = vector
    e = next(p for p in analyse(ws, inputs, design).preconditions if p.key == "e")
    assert e.holds is None and abs(e.detail_values["rho"]) < 0.01  # no shared direction: not shown


def test_the_secondary_endpoint_pairs_held_out_losses_by_draw_and_seed(tmp_path):
    ws = Workspace(tmp_path / "home")
    inputs, design = _study(ws, draws=[0, 1], seeds=[0, 1, 2])
    for s in (0, 1, 2):
        inputs[DownstreamLoss(arm="sft", draw=-1, seed=s).key] = _loss(ws, f"sft {s}", 0.30 + 0.01 * s)
        for d in (0, 1):  # CapVector 0.05 lower than the shared SFT run of its seed, ± a little
            inputs[DownstreamLoss(arm="capvector", draw=d, seed=s).key] = _loss(
                ws, f"cv {d} {s}", 0.25 + 0.01 * s + 0.002 * d
            )
    report = analyse(ws, inputs, design)
    (c,) = [c for c in report.heldout_loss if (c.arm, c.baseline) == ("capvector", "sft")]
    assert c.n_pairs == 6 and c.difference == pytest.approx(-0.049, abs=1e-9)
    assert c.ci_low < c.difference < c.ci_high < 0


def test_an_adapter_arms_merge_error_is_reported_beside_its_held_out_loss(tmp_path):
    """An arm evaluated as an adapter (LoRA-SP) carries merged − as-trained loss; a dense arm none."""
    from capvector.flows.study.report import heldout_loss_section

    ws = Workspace(tmp_path / "home")
    inputs, design = _study(ws, draws=[0], seeds=[0, 1, 2])
    for s in (0, 1, 2):
        inputs[DownstreamLoss(arm="sft", draw=-1, seed=s).key] = _loss(ws, f"sft {s}", 0.30)
        as_trained, merged = 0.25 + 0.01 * s, 0.45 + 0.02 * s  # the merge loses 0.20, 0.21, 0.22
        inputs[DownstreamLoss(arm="capvector", draw=0, seed=s).key] = _loss(ws, f"cv {s}", as_trained, merged)
    report = analyse(ws, inputs, design)
    assert set(report.merge_errors) == {"capvector"}
    error = report.merge_errors["capvector"]
    assert error.n_runs == 3 and error.mean == pytest.approx(0.21)
    assert error.ci_low < 0.20 and error.ci_high > 0.22
    (c,) = [c for c in report.heldout_loss if (c.arm, c.baseline) == ("capvector", "sft")]
    assert c.arm_mean == pytest.approx(0.26)  # the comparison uses the loss as trained, not the merge
    markdown = "\n".join(heldout_loss_section(report))
    assert "merge error" in markdown and "+0.2100" in markdown


def test_a_gate_reads_each_budget_and_its_declared_rule(tmp_path):
    """SFT from θ_ao far ahead of SFT at the first budget and level at the final one: the analysis
    compares every budget, the gate's reading calls (c′) shown on the endpoint and the secondary "a
    faster start, not a better end" shown; an interval wholly under the 5-point bar is a clean negative."""
    from capvector.flows.study.report import faster_start, gate_reading

    ws = Workspace(tmp_path / "home")
    inputs, design = _study(ws, draws=[0, 1, 2], seeds=[0, 1, 2])
    rng = np.random.default_rng(1)
    for d in (0, 1, 2):
        for s in (0, 1, 2):
            for b, p in ((10, 0.95), (20, 0.3)):
                key = TestEvaluation(arm="sft_from_ao", draw=d, seed=s, budget=b).key
                inputs[key] = _evaluation(ws, f"fast {d} {s} {b}", p, rng)
    report = analyse(ws, inputs, design.model_copy(update={"stage": "gate"}))
    budgets = {c.budget for c in report.comparisons if (c.arm, c.baseline) == ("sft_from_ao", "sft")}
    assert budgets == {ENDPOINT, 10, 20}
    endpoint = report.comparison("sft_from_ao", "sft")
    assert gate_reading(endpoint) == "shown"
    assert faster_start(report, "sft_from_ao", "sft").startswith("shown: @10 ")
    assert faster_start(report, "capvector", "sft").startswith("not shown")  # ahead at the final budget too
    assert "sft_from_ao-sft" in report.designs_for_5_points
    assert gate_reading(endpoint.model_copy(update={"ci_low": -3.0, "ci_high": 4.0})) == "clean negative"
    assert gate_reading(endpoint.model_copy(update={"ci_low": -3.0, "ci_high": 6.0})) == "not settled"
    both = gate_reading(endpoint.model_copy(update={"ci_low": 0.5, "ci_high": 4.5}))
    assert both.startswith("shown") and "clean negative" in both
    assert gate_reading(None) == "not settled"
