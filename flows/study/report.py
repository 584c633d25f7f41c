"""A study's report in Markdown: the headline comparisons with their CIs, the preconditions, the design;
a sweep's, its α × λ table.

Rendered from the `study` artifact (capvector.tasks.steps.study_analysis), plus the time per training step of
each arm, read from its checkpoints' records (timings are never part of the analysed document).
"""

from __future__ import annotations

import math
import statistics
from typing import Any

from capvector.artifacts.scores import read_episodes
from capvector.flows.recipe.config import lambda_label
from capvector.flows.study.forms_report import forms_section
from capvector.stats.paired_differences import ENDPOINT, Comparison, CurvePoint
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.steps.study_analysis import StudyReport

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
    "meta_sft_dose": "θ_meta at the dose α (no orthogonal loss)",
    "capvector": "CapVector",
    "null_capvector": "null vector",
    "sft_from_ao": "SFT from θ_ao",
    "sft_from_ft": "SFT from θ_ft",
}
VERDICT = {True: "holds", False: "fails", None: "not shown (CI includes 0)"}
WORTH_CARRYING = 5.0
"""Points: the smallest difference this project carries as a finding (the MDD every design is sized for,
and the bar under which a whole interval reads as a clean negative)."""
GATE_COMPARISONS = (("c′", "sft_from_ao", "sft"), ("c", "sft_from_ao", "sft_from_ft"))


def sweep_markdown(doc: dict[str, Any]) -> str:
    """An α × λ sweep's selection (`capvector sweep`; also one the sweep flow recorded before a sweep was a
    study) as a table: each cell's α, λ and validation success, the chosen one marked."""
    lines = ["| α | λ | validation success |", "|---|---|---|"]
    for r in doc["grid"]:
        mark = " **(best)**" if r == doc["best"] else ""
        lines.append(f"| {r['alpha']} | {lambda_label(r)} | {100 * r['validation_success']:.1f}%{mark} |")
    return "\n".join(lines) + "\n"


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
    if not c.testable:
        return f"{c.difference:+.1f} (untestable: no variance)"
    flag = (
        ""
        if c.reliable
        else ", one γ draw: not readable as the method's effect"
        if c.one_draw and c.df >= 2
        else ", too few seeds or draws: not readable"
    )
    return f"{c.difference:+.1f} [{c.ci_low:+.1f}, {c.ci_high:+.1f}] (df {c.df:.1f}{flag})"


def _components(c: Comparison) -> str:
    """The variance components (points²) a comparison's interval rests on; "?" where not separable."""
    values = c.components.model_dump()
    return ", ".join(f"{k} {'?' if v != v else f'{v:.0f}'}" for k, v in values.items() if v != 0)


def _all_comparisons(report: StudyReport) -> list[str]:
    """Every comparison with its df, the run-level cross-check and the variance components."""
    lines = [
        "",
        "## Every comparison: df, run-level cross-check, variance components",
        "",
        "The interval is mean ± t_df × a conservative method-of-moments standard error; the run-level "
        "interval uses only the spread of run means (draw and seed means), conditional on the test goals. "
        "An interval whose variance rests on a level with fewer than 3 units (2 seeds against a shared arm, "
        "2 draws) has df ≤ 1 and is marked not readable. A CI that includes 0 shows no difference; it "
        "does not show that the arms are equivalent (the MDD says what this design could have detected).",
        "",
        "| comparison | budget | difference [95 % CI] (df) | run-level [95 % CI] (df) | MDD | "
        "components (points²) |",
        "|---|---|---|---|---|---|",
    ]
    for c in report.comparisons:
        budget = "endpoint" if c.budget == ENDPOINT else str(c.budget)
        run_level = f"[{c.cluster_low:+.1f}, {c.cluster_high:+.1f}] ({c.cluster_df:.0f})"
        lines.append(
            f"| {NAMES.get(c.arm, c.arm)} − {NAMES.get(c.baseline, c.baseline)} | {budget} | {_cell(c)} | "
            f"{run_level} | {c.mdd:.1f} | {_components(c)} |"
        )
    return lines


def _mean_cell(p: CurvePoint) -> str:
    return f"{p.mean:.1f} [{p.ci_low:.1f}, {p.ci_high:.1f}]"


def _positive_control(report: StudyReport) -> list[str]:
    """Does the auxiliary objective help here at all (the testbed's positive control)?"""
    c = report.comparison("aux", "sft", ENDPOINT)
    if c is None:
        return []
    shown = c.testable and c.reliable and c.ci_low > 0
    big = shown and c.difference >= 10
    verdict = "met" if big else "benefit shown, below 10 points" if shown else "not shown"
    return [
        "",
        f"Positive control (auxiliary SFT − SFT at the endpoint, target ≥ 10 points with its interval above "
        f"0): {_cell(c)} — **{verdict}**.",
    ]


def _target(report: StudyReport, speed: dict[str, float]) -> list[str]:
    """The bar the study was built for, judged on point estimates and CIs at the primary endpoint."""
    vs_aux, vs_sft = report.comparison("capvector", "aux"), report.comparison("capvector", "sft")
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


def _sizing(report: StudyReport, key: str, c: Comparison | None) -> list[str]:
    if c is None or not c.testable:
        return []
    powered = "meets" if c.mdd <= WORTH_CARRYING else "does not meet"
    lines = [
        "",
        f"Minimum detectable difference of {NAMES[c.arm]} − {NAMES[c.baseline]} at the endpoint: "
        f"**{c.mdd:.1f} points** (80 % power, two-sided 5 %); this design {powered} the 5-point bar.",
    ]
    needed = report.designs_for_5_points.get(key)
    if c.mdd > WORTH_CARRYING:
        lines.append(
            f"From this study's variance components, an MDD ≤ 5 would take {needed.n_draws} draws × "
            f"{needed.n_seeds} seeds × {needed.n_goals_per_task} goals per task (MDD {needed.mdd:.1f})."
            if needed
            else "No design up to 20 draws × 20 seeds × 300 goals per task reaches an MDD of 5 here."
        )
    return lines


def _replicates(draws: list[int], k: int) -> str:
    if k == 1:
        return ""
    return f" in {len(draws) // k} replicates of {k} (CapVector's arms per replicate γ̄^r, the unit)"


def _grids(workspace: Workspace, report: StudyReport) -> list[str]:
    """Every selection's whole grid: each cell's validation success and its standard error over the
    validation goals (a goal's success averaged over the cell's budgets), the chosen cell in bold."""
    lines = []
    for sel in report.selections.values():
        doc = workspace.api.store.open_json(sel)
        params = doc["parameters"]
        ids = [e for row in doc["grid"] for e in row["evaluation_ids"]]
        episodes = read_episodes(workspace.api, ids).set_index("evaluation_id")
        lines += [
            "",
            f"Grid of {doc['name']} ({len(doc['grid'])} cells; validation success %, ± its standard error "
            "over goals):",
            "",
            "| " + " | ".join(params) + " | validation success | ± SE | goals |",
            "|" + "---|" * (len(params) + 3),
        ]
        for row in doc["grid"]:
            per_goal = episodes.loc[row["evaluation_ids"]].groupby(["task", "seed"])["success"].mean()
            se = 100 * per_goal.std(ddof=1) / math.sqrt(len(per_goal)) if len(per_goal) > 1 else math.nan
            best = all(row[p] == doc["best"][p] for p in params)
            mark = "**" if best else ""
            cells = " | ".join(f"{mark}{row[p]:g}{mark}" for p in params)
            lines.append(f"| {cells} | {100 * row['validation_success']:.1f} | {se:.1f} | {len(per_goal)} |")
    return lines


def _design(report: StudyReport) -> list[str]:
    """The title and what was run, so every number below can be read against its design."""
    d = report.design
    final = d.final_budget
    budgets = ", ".join(str(b) for b in d.endpoint_budgets)
    units = (
        f"{len(d.draws)} γ draw(s){_replicates(d.draws, d.draws_per_replicate)} × "
        if d.draws
        else f"no γ (arms from θ_pt: {', '.join(d.arms)}; no extraction, no gate) × "
    )
    return [
        f"# Study `{d.name}`",
        "",
        f"Design: {units}{len(d.seeds)} "
        f"training seed(s); {report.goals_per_task} test "
        f"goals per task × {len(report.tasks)} tasks ({', '.join(report.tasks)}), the same goals for every "
        f"checkpoint. Primary endpoint (declared in the preset): **mean success over {budgets} downstream "
        f"steps** (the area under the success-vs-steps curve); secondary: after {final}. Differences in "
        f"points, paired by draw, seed and goal, with 95 % t intervals (df in brackets; see the last "
        f"section for the run-level cross-check and the variance components).",
    ]


def gate_reading(c: Comparison | None) -> str:
    """The rule declared for the gate's comparisons: shown (interval above 0), clean negative (the whole
    interval below the bar a difference must clear to be carried), else not settled."""
    if c is None or not c.testable or not c.reliable:
        return "not settled"
    below_bar = c.ci_high < WORTH_CARRYING
    if c.ci_low > 0:  # both rules can hold: a difference shown, and shown to be small
        return "shown, and below the bar (a clean negative too)" if below_bar else "shown"
    return "clean negative" if below_bar else "not settled"


def faster_start(report: StudyReport, arm: str, baseline: str) -> str:
    """The declared secondary: ahead at the first budget (interval above 0) but not at the final one
    (its interval includes 0 or lies below): "a faster start, not a better end"."""
    first_budget, final_budget = min(report.design.endpoint_budgets), report.design.final_budget
    first = report.comparison(arm, baseline, first_budget)
    final = report.comparison(arm, baseline, final_budget)
    if first is None or final is None or first_budget == final_budget:
        return "not measured"
    if not (first.testable and first.reliable and final.testable and final.reliable):
        return "not readable"
    shown = first.ci_low > 0 and final.ci_low <= 0
    verdict = "shown" if shown else "not shown"
    return f"{verdict}: @{first_budget} {_cell(first)}, @{final_budget} {_cell(final)}"


def _gate_reading(report: StudyReport) -> list[str]:
    """(c′) and (c) read by the declared rule, each with its MDD and the design that would settle it."""
    lines = [
        "",
        "Reading of (c′) and (c) at the primary endpoint by the rule declared for the gate: **shown** when "
        f"the 95 % interval's low end is above 0; **clean negative** when its high end is below "
        f"{WORTH_CARRYING:.0f} points (whatever θ_ao adds is smaller than a difference worth carrying); "
        f"**not settled** otherwise, or where the interval is not readable.",
        "",
        "| precondition | comparison | endpoint [95 % CI] (df) | reading | MDD | a design for MDD ≤ "
        f"{WORTH_CARRYING:.0f} | faster start, not a better end |",
        "|---|---|---|---|---|---|---|",
    ]
    for key, arm, baseline in GATE_COMPARISONS:
        c = report.comparison(arm, baseline, ENDPOINT)
        mdd = f"{c.mdd:.1f}" if c is not None and c.testable else "—"
        lines.append(
            f"| ({key}) | {NAMES[arm]} − {NAMES[baseline]} | {_cell(c)} | **{gate_reading(c)}** | {mdd} | "
            f"{_design_for_the_bar(report, c)} | {faster_start(report, arm, baseline)} |"
        )
    return lines


def _design_for_the_bar(report: StudyReport, c: Comparison | None) -> str:
    """The cheapest design whose MDD would clear the bar, as the analysis sized it from `c`'s components."""
    if c is None or not c.testable:
        return "—"
    if c.mdd <= WORTH_CARRYING:
        return "met by this design"
    needed = report.designs_for_5_points.get(f"{c.arm}-{c.baseline}")
    if needed is None:
        return "—"
    goals = needed.n_goals_per_task
    return f"{needed.n_draws} draws × {needed.n_seeds} seeds × {goals} goals (MDD {needed.mdd:.1f})"


def _gate(report: StudyReport) -> list[str]:
    """Why CapVector's arms are missing: the gate stopped the study before them, or the study was
    declared gate-only (its stage is the gate's and its gate passed); at the gate stage, how (c′) and (c)
    read by the declared rule."""
    if report.design.stage != "gate" and report.gate is None:
        return []
    if report.gate is None:
        lines = [
            "",
            "## Gate: preconditions (c) and (c′) shown",
            "",
            "This study was declared gate-only: it tests the preconditions and ends at its gate. "
            "CapVector's arms (θ_meta, the orthogonal loss, the null vector) are not part of it.",
        ]
    else:
        lines = [
            "",
            "## Gate: the question is untestable here",
            "",
            report.gate,
            "",
            "CapVector's arms (θ_meta, the orthogonal loss, the null vector) were not run.",
        ]
    return lines + (_gate_reading(report) if report.design.stage == "gate" else [])


def _headline(report: StudyReport) -> list[str]:
    """CapVector against each baseline with its MDD; without CapVector's arms, the positive control's MDD."""
    if report.gate is not None or report.comparison("capvector", "sft", ENDPOINT) is None:
        return _sizing(report, "aux-sft", report.comparison("aux", "sft", ENDPOINT))
    final = report.design.final_budget
    lines = ["", "## Headline", "", "| comparison | endpoint (primary) | @ " + f"{final} (final) | MDD |"]
    lines.append("|---|---|---|---|")
    for arm, baseline in HEADLINE:
        p, f = report.comparison(arm, baseline, ENDPOINT), report.comparison(arm, baseline, final)
        mdd = f"{p.mdd:.1f}" if p and p.testable else "—"
        lines.append(f"| {NAMES[arm]} − {NAMES[baseline]} | {_cell(p)} | {_cell(f)} | {mdd} |")
    return lines + _sizing(report, "capvector-sft", report.comparison("capvector", "sft", ENDPOINT))


def _preconditions(report: StudyReport) -> list[str]:
    """Each precondition's outcome, so a headline is read only where what it rests on holds."""
    if not report.preconditions:  # a study whose arms need no γ
        return []
    lines = ["", "## Preconditions", "", "| | claim | outcome | evidence |", "|---|---|---|---|"]
    for p in report.preconditions:
        outcome = VERDICT[p.holds] if p.measured else "not measured"
        lines.append(f"| ({p.key.replace('_prime', '′')}) | {p.claim} | {outcome} | {p.detail} |")
    return lines


def _other_comparisons(report: StudyReport) -> list[str]:
    """The comparisons that locate the effect (where SFT starts from, the orthogonal loss)."""
    if not report.design.draws:  # a study whose arms need no γ: its comparisons are the forms section's
        return []
    budgets = sorted(set(report.design.endpoint_budgets) | {report.design.final_budget})
    lines = [
        "",
        "## Other comparisons",
        "",
        "| comparison | endpoint | " + " | ".join(f"@ {b}" for b in budgets) + " |",
        "|---|---|" + "---|" * len(budgets),
    ]
    others = (("aux", "sft"), ("sft_from_ao", "sft_from_ft"), ("sft_from_ao", "sft"), ("meta_sft", "sft"))
    if "meta_sft_dose" in report.design.arms:
        others += (("meta_sft_dose", "sft"), ("meta_sft_dose", "meta_sft"))
    for arm, baseline in others:
        cells = [_cell(report.comparison(arm, baseline, b)) for b in (ENDPOINT, *budgets)]
        lines.append(f"| {NAMES[arm]} − {NAMES[baseline]} | " + " | ".join(cells) + " |")
    return lines


def heldout_loss_section(report: StudyReport) -> list[str]:
    """The held-out action loss: a continuous secondary that sees differences success rates round away."""
    if not report.heldout_loss:
        return []
    lines = [
        "",
        "## Held-out action loss on D_down (secondary, continuous; lower is better)",
        "",
        "| comparison | difference [95 % CI] | arm | baseline | pairs |",
        "|---|---|---|---|---|",
    ]
    for c in report.heldout_loss:
        lines.append(
            f"| {NAMES.get(c.arm, c.arm)} − {NAMES.get(c.baseline, c.baseline)} | {c.difference:+.4f} "
            f"[{c.ci_low:+.4f}, {c.ci_high:+.4f}] | {c.arm_mean:.4f} | {c.baseline_mean:.4f} | "
            f"{c.n_pairs} |"
        )
    lines += ["", "Paired by draw and seed; a t interval over the pairs (approximate, see the analysis)."]
    if report.merge_errors:
        lines += [
            "",
            "LoRA-SP checkpoints are measured as they are evaluated, with the adapter applied to their init. "
            "Their dense merge (the checkpoint file, from which vectors are taken) approximates that "
            "input-conditioned adapter. The merge's error is merged − as-trained held-out loss, mean over "
            "runs [95 % CI]:",
            "",
            "| arm | merge error | runs |",
            "|---|---|---|",
        ]
        for arm, e in report.merge_errors.items():
            lines.append(
                f"| {NAMES.get(arm, arm)} | {e.mean:+.4f} [{e.ci_low:+.4f}, {e.ci_high:+.4f}] | {e.n_runs} |"
            )
    return lines


def _curve_row(arm: str, points: list[CurvePoint], budgets: list[int], speed: dict[str, float]) -> str:
    by = {p.budget: p for p in points}
    cells = [_mean_cell(by[b]) if b in by else "—" for b in budgets]
    sec = speed.get(arm)
    ratio = f"{sec / speed['sft']:.2f}" if sec and speed.get("sft") else "—"
    timing = f" | {sec:.4f} | {ratio} |" if sec else " | — | — |"
    return f"| {NAMES.get(arm, arm)} | " + " | ".join(cells) + timing


def _curves(report: StudyReport, speed: dict[str, float]) -> list[str]:
    """Success per arm at every budget beside its time per step: what an arm costs next to what it gains."""
    budgets = sorted({p.budget for points in report.curves.values() for p in points})
    lines = [
        "",
        "## Success vs downstream steps (mean % [95 % CI]; 0: the checkpoint a run starts from)",
        "",
    ]
    lines.append("| arm | " + " | ".join(str(b) for b in budgets) + " | s/step | × SFT |")
    lines.append("|---|" + "---|" * (len(budgets) + 2))
    return lines + [_curve_row(arm, points, budgets, speed) for arm, points in report.curves.items()]


def _figures(figures: dict[str, str]) -> list[str]:
    lines = []
    for title, path in figures.items():
        lines += ["", f"![{title}]({path})"]
    return lines


def _chosen(chosen: dict[str, float]) -> str:
    """The chosen settings, saying which form λ took (scaled to the gradient, or the paper's absolute)."""
    return "; ".join(f"{k.replace('_', ' ')} {v:g}" for k, v in chosen.items()) + (
        " (λ as a multiple of ‖∇ action loss‖/‖γ‖)."
        if "lambda_relative" in chosen or "lambda_scale" in chosen  # lambda_scale: its name until 2026-11
        else " (λ absolute, the paper's form)."
        if "lambda_absolute" in chosen
        else "."
    )


def _choices(report: StudyReport) -> list[str]:
    """The settings chosen on validation goals and the `selection` artifacts that record each choice (or,
    where nothing was chosen, the settings the preset gave)."""
    title = "## Choices (validation goals, tuning seed, at the primary endpoint; each a `selection` artifact)"
    if report.design.given:
        title = "## Settings (given by the preset: nothing was chosen, no tuning run)"
    lines = [
        "",
        title,
        "",
        _chosen(report.design.chosen),
        "",
    ]
    return lines + [
        f"- {name}: `{sel[:12]}` (`capvector lineage {sel[:12]}`)" for name, sel in report.selections.items()
    ]


def _edge(report: StudyReport) -> list[str]:
    """A choice at the end of its grid is a bound, not an optimum."""
    edge = report.design.at_edge()
    if not edge:
        return []
    return [f"\nChosen at the edge of its grid: {', '.join(edge)} (a wider grid might choose beyond)."]


def _timing_note() -> list[str]:
    """How the times per step were measured, so their ratios are not over-read."""
    return [
        "\nTime per step: median over an arm's runs of training time / steps (the λ calibration before "
        "training excluded), runs sharing 2 cores with other steps, so ratios are rough."
    ]


def study_markdown(workspace: Workspace, report: StudyReport, figures: dict[str, str] | None = None) -> str:
    """The report; `figures` maps a figure's title to its path relative to the Markdown file."""
    speed = seconds_per_step(workspace, report)
    lines = [
        *_design(report),
        *_gate(report),
        *_positive_control(report),
        *_headline(report),
        *_target(report, speed),
        *_preconditions(report),
        *_other_comparisons(report),
        *heldout_loss_section(report),
        *forms_section(workspace, report),
        *_curves(report, speed),
        *_all_comparisons(report),
        *_figures(figures or {}),
        *_choices(report),
        *_grids(workspace, report),
        *_edge(report),
        *_timing_note(),
    ]
    return "\n".join(lines) + "\n"
