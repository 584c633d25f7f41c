"""A study's report as files: Markdown and its PNG figures, written side by side.

Four figures drawn from the `study` artifact alone: success vs
downstream steps per arm (budget 0 is the checkpoint a run starts from) with its 95 % band drawn light,
each run's own mean as a point and n in the legend, the y range fitted to what is drawn so a wide band
at a small design does not flatten the rest; a forest plot of the paired differences at the primary
endpoint with each comparison's MDD marked; the endpoint per task and arm with a 95 % t interval over
runs and n; and γ (precondition (e)'s values): its norm against the seed-noise reference and the
signal's norm, and the cosines between draws, with θ_ft − θ_pt and between replicates. A fifth reads
the final checkpoints' records: each arm's training action-loss curves (median and range over runs).
A study of fine-tuning forms adds its own three (capvector.flows.study.forms_figures).
"""

from __future__ import annotations

import math
import statistics
from pathlib import Path
from typing import Any

from capvector.flows.study.forms_figures import plot_active_ranks, plot_capacity, plot_forms
from capvector.flows.study.plot_style import plt, y_range
from capvector.flows.study.report import NAMES, load_study_report, study_markdown
from capvector.stats.paired_differences import ENDPOINT
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.steps.evaluation import videos_of
from capvector.tasks.steps.study_analysis import StudyReport

COLOURS = {
    "sft": "#4c72b0",
    "aux": "#dd8452",
    "capvector": "#c44e52",
    "meta_sft": "#8172b3",
    "meta_sft_dose": "#da8bc3",
    "null_capvector": "#937860",
    "sft_from_ao": "#55a868",
    "sft_from_ft": "#8c8c8c",
}


def _n_label(arm: str, points: list[Any]) -> str:
    p = points[-1]
    draws = f"{p.n_draws} draws × " if p.n_draws > 1 else ""
    return f"{NAMES.get(arm, arm)} (n = {draws}{p.n_seeds} seeds × {p.n_goals} goals)"


def plot_curves(report: StudyReport, path: Path) -> Path:
    """Mean per arm with its 95 % interval as a light error bar at each budget (a band per arm filled
    in would cover the others when a small design makes it span most of 0-100), each run's mean success
    over its goals as a small point beside it (arms offset along x), n in the legend; the y range fitted
    to the means, points and intervals (within 0-100), never under 20 points tall."""
    fig, ax = plt.subplots(figsize=(7.2, 4.2))
    arms = list(report.curves)
    budgets = sorted({p.budget for points in report.curves.values() for p in points})
    gap = min((b - a for a, b in zip(budgets, budgets[1:], strict=False)), default=1) or 1
    shown: list[float] = []
    for i, (arm, points) in enumerate(report.curves.items()):
        offset = (i - (len(arms) - 1) / 2) * 0.06 * gap / max(len(arms) / 4, 1)
        steps = [p.budget + offset for p in points]
        colour = COLOURS.get(arm)
        low, high = [p.ci_low for p in points], [p.ci_high for p in points]
        means = [p.mean for p in points]
        ax.errorbar(
            steps,
            means,
            yerr=[
                [m - lo for m, lo in zip(means, low, strict=True)],
                [h - m for m, h in zip(means, high, strict=True)],
            ],
            fmt="none",
            ecolor=colour,
            elinewidth=1.0,
            capsize=3,
            alpha=0.45,
        )
        ax.plot(steps, means, marker="o", label=_n_label(arm, points), color=colour, lw=1.8)
        shown += [*low, *high, *(p.mean for p in points)]
        per_run = report.run_curves.get(arm, [])
        if per_run:
            xs, ys = [r.budget + offset for r in per_run], [r.success for r in per_run]
            ax.scatter(xs, ys, s=10, color=colour, alpha=0.55, lw=0, zorder=3)
            shown += ys
    ax.set_ylim(*y_range(shown))
    ax.set_xlabel("downstream training steps (0: the starting checkpoint)")
    ax.set_ylabel("test success (%)")
    ax.set_title(
        "Success vs steps: mean (line), 95 % CI over draws, seeds and goals (bars),\n"
        "each run's mean over its goals (points)",
        fontsize=9,
    )
    ax.legend(fontsize=7, ncol=2, loc="upper center", bbox_to_anchor=(0.5, -0.16), frameon=False)
    ax.grid(alpha=0.3)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_forest(report: StudyReport, path: Path) -> Path | None:
    rows = [c for c in report.comparisons if c.budget == ENDPOINT]
    if not rows:
        return None
    fig, ax = plt.subplots(figsize=(7.2, 0.5 * len(rows) + 1.8))
    for y, c in enumerate(reversed(rows)):
        colour = "#c44e52" if c.arm == "capvector" else "#4c72b0"
        if c.testable:
            ax.plot([c.ci_low, c.ci_high], [y, y], color=colour, lw=2)
            ax.plot([-c.mdd, c.mdd], [y - 0.22, y - 0.22], color="#999999", lw=1, ls=":")
        marker = "o" if c.testable and c.reliable else "x"
        ax.plot([c.difference], [y], marker=marker, color=colour)
    ax.axvline(0, color="black", lw=0.8)
    labels = [f"{NAMES.get(c.arm, c.arm)} − {NAMES.get(c.baseline, c.baseline)}" for c in reversed(rows)]
    ax.set_yticks(range(len(rows)), labels, fontsize=8)
    ax.set_xlabel("difference at the primary endpoint (points)\ndotted: ±MDD; ×: df < 2 or no variance")
    ax.set_title("Paired differences, 95 % CI", fontsize=10)
    ax.grid(axis="x", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _half(value: float, endpoint: Any, side: str) -> float:
    """An error bar's length from `value` to the interval's `side` (0 where there is no interval)."""
    bound = getattr(endpoint, side, math.nan) if endpoint is not None else math.nan
    return 0.0 if math.isnan(bound) else abs(bound - value)


def plot_per_task(report: StudyReport, path: Path) -> Path | None:
    """Bars of the endpoint per task and arm, with a 95 % t interval over runs and n (runs × goals per
    task) in the legend (`per_task_intervals`; a report from before them: the means alone)."""
    if not report.per_task:
        return None
    intervals = report.per_task_intervals
    arms = list(report.per_task)
    tasks = report.tasks
    width = 0.8 / len(arms)
    fig, ax = plt.subplots(figsize=(max(6.4, 0.9 * len(tasks) + 2.5), 4.2))
    for i, arm in enumerate(arms):
        xs = [t + (i - (len(arms) - 1) / 2) * width for t in range(len(tasks))]
        values = [report.per_task[arm].get(task, 0.0) for task in tasks]
        found = intervals.get(arm, {})
        n_runs = max((found[t].n_runs for t in tasks if t in found), default=0)
        n_goals = max((found[t].n_goals for t in tasks if t in found), default=0)
        label = NAMES.get(arm, arm) + (f" (n = {n_runs} runs × {n_goals} goals)" if n_runs else "")
        ax.bar(xs, values, width, label=label, color=COLOURS.get(arm))
        if found:
            low = [_half(v, found.get(t), "ci_low") for v, t in zip(values, tasks, strict=True)]
            high = [_half(v, found.get(t), "ci_high") for v, t in zip(values, tasks, strict=True)]
            ax.errorbar(xs, values, yerr=[low, high], fmt="none", ecolor="#333333", elinewidth=0.9, capsize=2)
    ax.set_xticks(range(len(tasks)), tasks, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("success at the endpoint (%)")
    ax.set_ylim(0, 103)
    ax.set_title("Per task: mean success over the endpoint's budgets, 95 % t interval over runs", fontsize=10)
    ax.legend(fontsize=7, ncol=2, loc="upper center", bbox_to_anchor=(0.5, -0.3), frameon=False)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def _per(values: dict[str, float], prefix: str) -> list[tuple[str, float]]:
    """(suffix, value) of the finite `prefix<suffix>` keys, in key order."""
    found = [(k.removeprefix(prefix), x) for k, x in values.items() if k.startswith(prefix)]
    return sorted((k, x) for k, x in found if not math.isnan(x))


def _label_bar(ax: Any, x: float, value: float, top: float, text: str) -> None:
    """`text` just above the bar or what is drawn over it (`top`), below a negative bar."""
    up = value >= 0
    ax.annotate(
        text,
        (x, top if up else value),
        xytext=(0, 4 if up else -4),
        textcoords="offset points",
        ha="center",
        va="bottom" if up else "top",
        fontsize=8,
    )


def _finite(v: dict[str, float], key: str) -> bool:
    return key in v and not math.isnan(v[key])


def _interval(ax: Any, x: int, v: dict[str, float], key: str) -> float:
    """Draw `key`'s interval when measured; the top of what is drawn at x."""
    if not _finite(v, f"{key}_low"):
        return v[key]
    low, high = v[f"{key}_low"], v[f"{key}_high"]
    ax.errorbar(x, v[key], yerr=[[v[key] - low], [high - v[key]]], fmt="none", ecolor="#333333", capsize=3)
    return max(v[key], high)


def _norm_bars(v: dict[str, float], n_draws: int) -> list[tuple[str, str]]:
    """(key, tick label) of the measured norms, γ's first."""
    return [
        (k, label)
        for k, label in (
            ("gamma_norm", f"‖γ^d‖ (mean of {n_draws or 'the'} draws;\npoints: each draw)"),
            ("signal_norm", "‖ŝ‖: the signal\nshared by draws"),
            ("seed_noise_norm", "‖θ_ft^d − θ_ft^d′‖\n(seed noise)"),
        )
        if _finite(v, k)
    ]


def _plot_norms(ax: Any, v: dict[str, float]) -> None:
    """γ's size against the seed-noise reference: is it more than what another seed would give?"""
    per_draw = _per(v, "gamma_norm_draw_")
    norms = _norm_bars(v, len(per_draw))
    colours = {"gamma_norm": "#c44e52", "signal_norm": "#dd8452", "seed_noise_norm": "#8c8c8c"}
    tops = []
    for x, (key, _) in enumerate(norms):
        ax.bar(x, v[key], 0.6, color=colours[key])
        top = _interval(ax, x, v, key)
        if key == "gamma_norm" and per_draw:
            ax.scatter([x] * len(per_draw), [n for _, n in per_draw], s=14, color="black", zorder=3)
            top = max(top, *(n for _, n in per_draw))
        _label_bar(ax, x, v[key], top, f"{v[key]:.3g}")
        tops.append(top)
    ax.set_ylim(0, 1.15 * max(tops, default=1) or 1)
    ax.set_xticks(range(len(norms)), [label for _, label in norms], fontsize=7.5)
    ax.set_ylabel("L2 norm over the vector's tensors")
    ax.set_title("Size: γ against the seed-noise reference", fontsize=9)


def _cosine_bars(v: dict[str, float], n_pairs: int) -> list[tuple[str, str]]:
    """(key, tick label) of the measured cosines, ρ̂ first."""
    return [
        (k, label)
        for k, label in (
            ("rho", f"ρ̂: cos(γ^d, γ^d′)\n(points: {n_pairs} pair{'s' if n_pairs != 1 else ''})"),
            ("cos_ft_reference", "cos(γ^d, θ_ft^d − θ_pt)\n(mean over draws)"),
            ("mean_vector_cos", "the draws' mean:\ncos with the signal\n(from ρ̂)"),
            ("replicate_cos", "cos(γ̄^r, γ̄^r′)\nbetween replicates"),
        )
        if _finite(v, k)
    ]


def _plot_cosines(ax: Any, v: dict[str, float]) -> None:
    """γ's direction: do draws agree with each other, with θ_ft − θ_pt, and between replicates?"""
    pairs = _per(v, "cos_draws_")
    cosines = _cosine_bars(v, len(pairs))
    shown = []
    for x, (key, _) in enumerate(cosines):
        ax.bar(x, v[key], 0.6, color="#55a868" if key == "replicate_cos" else "#4c72b0")
        top = _interval(ax, x, v, key)
        if key == "rho" and pairs:
            ax.scatter([x] * len(pairs), [c for _, c in pairs], s=14, color="black", zorder=3)
            top = max(top, *(c for _, c in pairs))
            shown += [c for _, c in pairs]
        if key == "replicate_cos" and _finite(v, "replicate_cos_predicted"):
            ax.plot([x - 0.3, x + 0.3], [v["replicate_cos_predicted"]] * 2, color="black", ls="--", lw=1)
        _label_bar(ax, x, v[key], top, f"{v[key]:+.2f}")
        shown += [v[key], v.get(f"{key}_low", v[key])]
    ax.axhline(0, color="black", lw=0.8)
    ax.set_ylim(min(-0.2, *(c - 0.15 for c in shown)), 1.1)
    ax.set_xticks(range(len(cosines)), [label for _, label in cosines], fontsize=7.5)
    ax.set_ylabel("cosine")
    interval_note = "95 % jackknife over draws" if _finite(v, "rho_low") else "no interval: it needs 3 draws"
    dashed = "; dashed: ρ̂'s prediction" if _finite(v, "replicate_cos_predicted") else ""
    ax.set_title(f"Direction ({interval_note}{dashed})", fontsize=9)


def plot_gamma(report: StudyReport, path: Path) -> Path | None:
    """Precondition (e)'s γ as two panels. Norms: ‖γ^d‖ per draw (points) and their mean, the signal's
    norm ‖ŝ‖ (with its jackknife interval from 3 draws), the seed-noise reference ‖θ_ft^d − θ_ft^d′‖.
    Cosines: ρ̂, the mean cos between draws (each pair a point; its interval from 3 draws), cos(γ^d,
    θ_ft^d − θ_pt), the cos with the signal ρ̂ implies for the draws' mean, and between replicates
    (measured, with ρ̂'s prediction dashed). None without (e)'s values."""
    e = next((p for p in report.preconditions if p.key == "e"), None)
    v = e.detail_values if e is not None else {}
    if "rho" not in v:
        return None
    fig, (left, right) = plt.subplots(1, 2, figsize=(9.6, 3.8), gridspec_kw={"width_ratios": [1, 1.35]})
    _plot_norms(left, v)
    _plot_cosines(right, v)
    for ax in (left, right):
        ax.grid(axis="y", alpha=0.3)
    fig.suptitle("Precondition (e): is there a γ shared by draws, beyond seed noise?", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _loss_curves(workspace: Workspace, report: StudyReport) -> dict[str, list[list[dict[str, Any]]]]:
    """Arm -> each final checkpoint's logged training curve (rows with `step` and `loss`)."""
    out = {}
    for arm, ids in report.final_checkpoints.items():
        curves = [(workspace.api.get(i).config or {}).get("curve") or [] for i in ids]
        out[arm] = [c for c in curves if c]
    return {arm: curves for arm, curves in out.items() if curves}


def plot_losses(workspace: Workspace, report: StudyReport, path: Path) -> Path | None:
    """Training action loss vs downstream step per arm: the median over its runs (line) and the range
    between the runs' lowest and highest (band), on a log scale; n runs in the legend. The action term
    alone (the curve's `action` column), so arms with extra terms (the auxiliary objective, the
    orthogonal penalty) are read on the same scale."""
    curves = _loss_curves(workspace, report)
    if not curves:
        return None
    fig, ax = plt.subplots(figsize=(7.2, 4.0))
    for arm, runs in curves.items():
        steps = sorted(set.intersection(*[{row["step"] for row in run} for run in runs]))
        by_step = [
            [next(r.get("action", r["loss"]) for r in run if r["step"] == s) for run in runs] for s in steps
        ]
        colour = COLOURS.get(arm)
        ax.fill_between(steps, [min(v) for v in by_step], [max(v) for v in by_step], color=colour, alpha=0.15)
        label = f"{NAMES.get(arm, arm)} (n = {len(runs)})"
        ax.plot(steps, [statistics.median(v) for v in by_step], color=colour, lw=1.6, label=label)
    ax.set_yscale("log")
    ax.set_xlabel("downstream training step")
    ax.set_ylabel("training action loss (log scale)")
    ax.set_title(
        "Training action loss per arm: median over runs (line), lowest to highest run (band)", fontsize=9
    )
    ax.legend(fontsize=7, ncol=2, loc="upper center", bbox_to_anchor=(0.5, -0.16), frameon=False)
    ax.grid(alpha=0.3, which="both")
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def latest_study_id(workspace: Workspace) -> str | None:
    _, rows = workspace.api.query_rows(
        "SELECT id FROM artifacts WHERE kind = 'study' ORDER BY created_at DESC LIMIT 1"
    )
    return str(rows[0][0]) if rows else None


def default_report_path(workspace: Workspace, study_id: str) -> Path:
    """Reports go into the home (`reports/`), never over a tracked file of the directory run from; a
    remote home's into its local cache folder, beside its run logs (`Path("s3://b/home")` was a local
    folder `s3:/b/home` in the directory run from)."""
    name = workspace.api.get(study_id).name.removeprefix("analyse study ").replace(" ", "-")
    return workspace.local_root / "reports" / f"{name}-{study_id[:12]}.md"


def write_study_report(workspace: Workspace, study_id: str, out: Path) -> Path:
    """`out` (Markdown) and its figures `<stem>_*.png` beside it; returns the Markdown path."""
    report = load_study_report(workspace, study_id)
    out.parent.mkdir(parents=True, exist_ok=True)
    drawn = {
        "Success vs downstream steps": plot_curves(report, out.parent / f"{out.stem}_curves.png"),
        "Paired differences at the endpoint": plot_forest(report, out.parent / f"{out.stem}_forest.png"),
        "Per task": plot_per_task(report, out.parent / f"{out.stem}_tasks.png"),
        "γ: norms and directions (precondition (e))": plot_gamma(
            report, out.parent / f"{out.stem}_gamma.png"
        ),
        "Training action loss per arm": plot_losses(workspace, report, out.parent / f"{out.stem}_losses.png"),
        "Endpoint vs trainable parameters": plot_forms(
            workspace, report, out.parent / f"{out.stem}_forms.png"
        ),
        "Endpoint vs rank": plot_capacity(workspace, report, out.parent / f"{out.stem}_capacity.png"),
        "Active ranks per module kind": plot_active_ranks(
            workspace, report, out.parent / f"{out.stem}_ranks.png"
        ),
    }
    figures = {title: p.name for title, p in drawn.items() if p is not None}
    markdown = study_markdown(workspace, report, figures) + _videos_section(workspace, study_id)
    out.write_text(markdown + f"\nStudy artifact: `{study_id}` (`capvector lineage {study_id[:12]}`).\n")
    return out


def _videos_section(workspace: Workspace, study_id: str) -> str:
    """Links to the rollout videos of the study's test evaluations (`evaluation.record_video`)."""
    tests = [p.id for p in workspace.api.get(study_id).parents if p.role == "test"]
    found = videos_of(workspace, tests)
    if not found:
        return ""
    lines = ["", "## Rollout videos", ""]
    for videos in found.values():
        lines += [f"- [{name}]({path})" for name, path in videos]
    return "\n".join(lines) + "\n"
