"""Issue 37, item 4: the study report's figures for the argument, from a StudyReport alone (the golden
study-smoke report with numbers set here): curves with n in the legend and each run's points, per-task
bars with intervals over runs, and the γ figure from precondition (e)'s values. Seconds: no study runs."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pandas as pd
import pytest

from capvector.flows.study import figures as study_figures
from capvector.flows.study import plot_style
from capvector.stats.paired_differences import ENDPOINT
from capvector.tasks.steps.study_analysis import StudyReport, _per_task_intervals

GOLDEN = Path(__file__).parent / "data" / "study_smoke_report.json"
PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture
def report() -> StudyReport:
    return StudyReport.model_validate(
        json.loads(GOLDEN.read_text()) | {"final_checkpoints": {}, "selections": {}}
    )


def test_per_task_intervals_are_over_runs_with_their_n():
    """Runs, not goals, are the unit: two runs at 50 % and 100 % (2 goals each) give 75 % with a t
    interval of 1 df, clipped to 0-100; one run gives no interval."""
    rows = [
        {"arm": "sft", "draw": -1, "seed": seed, "task": "reach-v3", "goal": goal, "budget": ENDPOINT,
         "success": float(ok)}
        for seed, oks in ((0, (1, 0)), (1, (1, 1)))
        for goal, ok in zip((7, 8), oks, strict=True)
    ] + [{"arm": "aux", "draw": -1, "seed": 0, "task": "reach-v3", "goal": 7, "budget": ENDPOINT,
          "success": 1.0}]  # fmt: skip
    got = _per_task_intervals(pd.DataFrame(rows))
    sft = got["sft"]["reach-v3"]
    assert (sft.mean, sft.n_runs, sft.n_goals) == (75.0, 2, 2)
    assert sft.ci_low == 0.0 and sft.ci_high == 100.0  # 75 ± 12.71 × 25 / √2, clipped
    aux = got["aux"]["reach-v3"]
    assert aux.n_runs == 1 and math.isnan(aux.ci_low) and math.isnan(aux.ci_high)


def test_the_curves_say_n_and_fit_their_y_range(report, tmp_path):
    labels = [study_figures._n_label(arm, points) for arm, points in report.curves.items()]
    assert "CapVector (n = 2 draws × 2 seeds × 3 goals)" in labels and "SFT (n = 2 seeds × 3 goals)" in labels
    assert plot_style.y_range([0.0, 0.0]) == (0.0, 20.0)  # all at 0: still readable
    assert plot_style.y_range([40.0, 55.0, 62.0]) == (35.0, 67.0)  # fitted, not 0-100
    assert plot_style.y_range([0.0, 100.0]) == (0.0, 100.0)
    assert plot_style.y_range([99.0, 100.0]) == (80.0, 100.0)
    assert report.run_curves["capvector"] and {p.budget for p in report.run_curves["capvector"]} == {0, 8, 16}
    path = study_figures.plot_curves(report, tmp_path / "curves.png")
    assert path.read_bytes()[:8] == PNG


def test_per_task_bars_carry_intervals_and_n(report, tmp_path):
    found = report.per_task_intervals["capvector"]["button-press-topdown-v3"]
    assert (found.n_runs, found.n_goals) == (4, 3)
    assert study_figures.plot_per_task(report, tmp_path / "tasks.png").read_bytes()[:8] == PNG


def test_the_gamma_figure_is_drawn_from_precondition_e(report, tmp_path):
    e = next(p for p in report.preconditions if p.key == "e")
    assert {"gamma_norm_draw_0", "gamma_norm_draw_1", "cos_draws_0_1"} <= set(e.detail_values)
    assert study_figures._per(e.detail_values, "gamma_norm_draw_") == [
        ("0", e.detail_values["gamma_norm_draw_0"]),
        ("1", e.detail_values["gamma_norm_draw_1"]),
    ]
    path = study_figures.plot_gamma(report, tmp_path / "gamma.png")
    assert path is not None and path.read_bytes()[:8] == PNG
    three = {"rho_low": -0.2, "rho_high": 0.4, "replicate_cos": 0.3, "replicate_cos_predicted": 0.25}
    e.detail_values.update(three | {"signal_norm_low": 0.0, "signal_norm_high": 0.1})
    assert study_figures.plot_gamma(report, tmp_path / "gamma3.png") is not None
    e.detail_values.clear()
    assert study_figures.plot_gamma(report, tmp_path / "none.png") is None  # no values: no figure
