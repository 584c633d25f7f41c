"""A study's report in Markdown: the headline comparisons with their CIs, the preconditions, the design.

Rendered from the `study` artifact (tasks.study_analysis), plus the time per training step of each
arm, read from its checkpoints' records (timings are never part of the analysed document).
"""

from __future__ import annotations

import statistics

from tasks.study_analysis import StudyReport
from tasks.study_statistics import Comparison, CurvePoint
from tasks.workspace import Workspace

HEADLINE = (
    ("capvector", "sft"),
    ("capvector", "aux"),
    ("capvector", "meta_sft"),
    ("capvector", "null_capvector"),
)
NAMES = {
    "sft": "SFT",
    "aux": "auxiliary SFT",
    "meta_sft": "θ_meta without the orthogonal loss",
    "capvector": "CapVector",
    "null_capvector": "null vector",
    "sft_from_ao": "SFT from θ_ao",
    "sft_from_ft": "SFT from θ_ft",
}
VERDICT = {True: "holds", False: "fails", None: "not shown (CI includes 0)"}


def load_study_report(workspace: Workspace, report_id: str) -> StudyReport:
    return StudyReport.model_validate(workspace.api.store.open_json(report_id))


def seconds_per_step(workspace: Workspace, report: StudyReport) -> dict[str, float]:
    """Arm -> median training seconds per step over its runs (from the checkpoints' run summaries)."""
    out = {}
    for arm, ids in report.final_checkpoints.items():
        speeds = [workspace.api.get(i).config["summary"]["steps_per_s"] for i in ids]
        speeds = [s for s in speeds if s]
        if speeds:
            out[arm] = 1.0 / statistics.median(speeds)
    return out


def _cell(c: Comparison | None) -> str:
    if c is None:
        return "—"
    return f"{c.difference:+.1f} [{c.ci_low:+.1f}, {c.ci_high:+.1f}]"


def _mean_cell(p: CurvePoint) -> str:
    """A success rate lies in [0, 100]: a t interval with few degrees of freedom can reach beyond."""
    return f"{p.mean:.1f} [{max(0.0, p.ci_low):.1f}, {min(100.0, p.ci_high):.1f}]"


def _find(report: StudyReport, arm: str, baseline: str, budget: int) -> Comparison | None:
    return next(
        (c for c in report.comparisons if (c.arm, c.baseline, c.budget) == (arm, baseline, budget)), None
    )


def _target(report: StudyReport, speed: dict[str, float]) -> list[str]:
    """The bar the study was built for, judged on point estimates and CIs at the primary endpoint."""
    primary = report.design.primary_budget
    vs_aux, vs_sft = _find(report, "capvector", "aux", primary), _find(report, "capvector", "sft", primary)
    if vs_aux is None or vs_sft is None:
        return []
    near_aux = -2 <= vs_aux.ci_low and vs_aux.ci_high <= 2
    above_sft = vs_sft.ci_low >= 5
    cost = speed["capvector"] / speed["sft"] if "capvector" in speed and "sft" in speed else None
    cheap = cost is not None and cost <= 1.1
    met = near_aux and above_sft and cheap
    return [
        "",
        f"Target (CapVector within 2 points of auxiliary SFT, ≥ 5 above SFT, ≤ 1.1× SFT's time per step, "
        f"at the primary endpoint): **{'met' if met else 'not met'}** — vs auxiliary SFT {_cell(vs_aux)} "
        f"({'within' if near_aux else 'not shown within'} ±2), vs SFT {_cell(vs_sft)} "
        f"({'≥ 5 shown' if above_sft else '≥ 5 not shown'}), time per step "
        f"{f'{cost:.2f}×' if cost is not None else 'not measured'} SFT's.",
    ]


def study_markdown(workspace: Workspace, report: StudyReport) -> str:
    d = report.design
    primary, final = d.primary_budget, d.final_budget
    lines = [f"# Study `{d.name}`", ""]
    lines += [
        f"Design: {len(d.draws)} γ draw(s) × {len(d.seeds)} training seed(s); {report.goals_per_task} test "
        f"goals per task × {len(report.tasks)} tasks ({', '.join(report.tasks)}), the same goals for every "
        f"checkpoint. Primary endpoint (declared in the preset): success after **{primary}** downstream "
        f"steps; secondary: after {final}. Differences in points, paired by draw, seed and goal, with "
        f"hierarchical-bootstrap 95 % CIs (tasks.study_statistics).",
        "",
        "## Headline",
        "",
        f"| comparison | @ {primary} (primary) | @ {final} (final) | MDD @ {primary} |",
        "|---|---|---|---|",
    ]
    for arm, baseline in HEADLINE:
        p, f = _find(report, arm, baseline, primary), _find(report, arm, baseline, final)
        mdd = f"{p.mdd:.1f}" if p else "—"
        lines.append(f"| {NAMES[arm]} − {NAMES[baseline]} | {_cell(p)} | {_cell(f)} | {mdd} |")
    main = _find(report, "capvector", "sft", primary)
    if main is not None:
        powered = "meets" if main.mdd <= 5 else "does not meet"
        lines += [
            "",
            f"Minimum detectable difference of CapVector − SFT at the primary endpoint: **{main.mdd:.1f} "
            f"points** (80 % power, two-sided 5 %); this design {powered} the 5-point bar.",
        ]
        needed = report.designs_for_5_points.get("capvector-sft")
        if main.mdd > 5:
            lines.append(
                f"From this study's variance components, an MDD ≤ 5 would take {needed.n_draws} draws × "
                f"{needed.n_seeds} seeds × {needed.n_goals_per_task} goals per task (MDD {needed.mdd:.1f})."
                if needed
                else "No design up to 20 draws × 20 seeds × 300 goals per task reaches an MDD of 5 here."
            )
    lines += _target(report, speed := seconds_per_step(workspace, report))
    lines += ["", "## Preconditions", "", "| | claim | outcome | evidence |", "|---|---|---|---|"]
    for p in report.preconditions:
        lines.append(f"| ({p.key}) | {p.claim} | {VERDICT[p.holds]} | {p.detail} |")
    lines += ["", "## Other comparisons", "", f"| comparison | @ {primary} | @ {final} |", "|---|---|---|"]
    for arm, baseline in (("aux", "sft"), ("sft_from_ao", "sft_from_ft"), ("meta_sft", "sft")):
        lines.append(
            f"| {NAMES[arm]} − {NAMES[baseline]} | {_cell(_find(report, arm, baseline, primary))} | "
            f"{_cell(_find(report, arm, baseline, final))} |"
        )
    budgets = sorted({p.budget for points in report.curves.values() for p in points})
    lines += ["", "## Success vs downstream steps (mean % [95 % CI])", ""]
    lines.append("| arm | " + " | ".join(str(b) for b in budgets) + " | s/step | × SFT |")
    lines.append("|---|" + "---|" * (len(budgets) + 2))
    for arm, points in report.curves.items():
        by = {p.budget: p for p in points}
        cells = [_mean_cell(by[b]) if b in by else "—" for b in budgets]
        sec = speed.get(arm)
        ratio = f"{sec / speed['sft']:.2f}" if sec and speed.get("sft") else "—"
        lines.append(
            f"| {NAMES.get(arm, arm)} | " + " | ".join(cells) + f" | {sec:.4f} | {ratio} |"
            if sec
            else f"| {NAMES.get(arm, arm)} | " + " | ".join(cells) + " | — | — |"
        )
    chosen = d.chosen
    lines += [
        "",
        "## Choices (validation goals, tuning seed; each a `selection` artifact)",
        "",
        f"extraction lr {chosen['extraction_lr']:g}; auxiliary weight {chosen['aux_weight']:g}; "
        f"α {chosen['alpha']:g}; λ {chosen['lambda_scale']:g} × ‖∇ action loss‖/‖γ‖.",
        "",
    ]
    for name, sel in report.selections.items():
        lines.append(f"- {name}: `{sel[:12]}` (`capvector lineage {sel[:12]}`)")
    edge = d.at_edge()
    if edge:
        lines.append(
            f"\nChosen at the edge of its grid: {', '.join(edge)} (a wider grid might choose beyond)."
        )
    lines.append(
        "\nTime per step: median over an arm's runs of training time / steps (the λ calibration before "
        "training excluded), runs sharing 2 cores with other steps, so ratios are rough."
    )
    return "\n".join(lines) + "\n"
