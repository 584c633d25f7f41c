"""The figures of a study of fine-tuning forms (issue 40's rank study), from the `study` artifact and the
final checkpoints' run summaries: endpoint success against trainable parameters, endpoint success
against rank (LoRA's r, LoRA-SP's bank, AdaLoRA's target rank) with full fine-tuning as a band, and the
active ranks per module kind of the rank-adaptive forms (each point one adapted layer of one run)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from matplotlib.ticker import NullFormatter

from capvector.core.vectors.spectrum import KIND_ORDER, module_kind
from capvector.flows.study.forms_report import FormRow, form_rows, run_summaries
from capvector.flows.study.plot_style import plt, y_range
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.steps.study_analysis import StudyReport

FORM_COLOURS = {"full": "#4c72b0", "LoRA": "#dd8452", "LoRA-SP": "#55a868", "AdaLoRA": "#c44e52"}
CAPACITY_KEYS = {"sft_lora": "lora.r", "sft_lora_sp": "lora_sp.bank_size", "sft_adalora": "adalora.target_r"}
"""The override that sets a form's rank: LoRA's r, LoRA-SP's bank, AdaLoRA's final rank budget."""


def plot_forms(workspace: Workspace, report: StudyReport, path: Path) -> Path | None:
    """A study of fine-tuning forms: each arm's endpoint success (95 % interval as a bar) against its
    trainable parameters (log scale), coloured by form, each point named by its arm; a form's variants
    joined by a line in order of size, so its dependence on capacity reads as the line's slope."""
    rows = [r for r in form_rows(workspace, report) if r.endpoint is not None and r.trainable_parameters]
    if not report.design.variants or not rows:
        return None
    fig, ax = plt.subplots(figsize=(7.2, 4.4))
    shown = _form_lines(ax, {r.arm: r.trainable_parameters for r in rows}, rows, annotate=True)
    ax.set_xscale("log")
    ax.xaxis.set_minor_formatter(NullFormatter())  # minor labels of a short log axis overlap
    _finish(
        ax, shown, rows[0], "trainable parameters (log scale)", "Endpoint success vs trainable parameters"
    )
    return _save(fig, path)


def capacity(report: StudyReport, arm: str) -> int | None:
    """The rank a variant declares (its `set` override of its form's rank), or None."""
    declared = report.design.variants.get(arm)
    key = CAPACITY_KEYS.get(declared["arm"]) if declared else None
    value = declared["set"].get(key) if key else None
    return int(value) if value is not None else None


def plot_capacity(workspace: Workspace, report: StudyReport, path: Path) -> Path | None:
    """Endpoint success against rank (log 2 scale), a line per form; full fine-tuning's mean and 95 %
    interval as a horizontal band, so "which rank matches full fine-tuning" reads off the band."""
    rows = [r for r in form_rows(workspace, report) if r.endpoint is not None]
    ranks = {r.arm: capacity(report, r.arm) for r in rows}
    ranked = [r for r in rows if ranks[r.arm]]
    if not ranked:
        return None
    fig, ax = plt.subplots(figsize=(7.2, 4.4))
    shown = _form_lines(ax, ranks, ranked, annotate=False)
    full = next((r.endpoint for r in rows if r.arm == "sft"), None)
    if full is not None:
        ax.axhspan(full.ci_low, full.ci_high, color=FORM_COLOURS["full"], alpha=0.15, lw=0)
        ax.axhline(full.mean, color=FORM_COLOURS["full"], lw=1.2, label="full fine-tuning (95 % CI band)")
        shown += [full.ci_low, full.ci_high]
    ax.set_xscale("log", base=2)
    values = sorted({ranks[r.arm] for r in ranked})
    ax.set_xticks(values, [str(v) for v in values])
    ax.xaxis.set_minor_formatter(NullFormatter())
    _finish(
        ax,
        shown,
        ranked[0],
        "rank (LoRA r, LoRA-SP bank, AdaLoRA target r; log 2 scale)",
        "Endpoint success vs rank",
    )
    return _save(fig, path)


def plot_active_ranks(workspace: Workspace, report: StudyReport, path: Path) -> Path | None:
    """Per module kind, a box per rank-adaptive arm of the active ranks of its adapted layers over its
    runs (LoRA-SP: the mean active rank over the calibration inputs; AdaLoRA: the rank its allocator
    kept), as a fraction of the arm's declared rank, so banks of different sizes share one axis."""
    arms = [
        a
        for a in report.design.variants
        if report.design.variants[a]["arm"] in ("sft_lora_sp", "sft_adalora")
    ]
    per_arm = {a: _layer_ranks(workspace, report, a) for a in arms}
    per_arm = {a: kinds for a, kinds in per_arm.items() if kinds}
    if not per_arm:
        return None
    kinds = [k for k in KIND_ORDER if any(k in v for v in per_arm.values())]
    fig, axes = plt.subplots(1, len(kinds), figsize=(2.6 * len(kinds) + 1, 3.8), sharey=True, squeeze=False)
    for ax, kind in zip(axes[0], kinds, strict=True):
        names = [a for a in per_arm if kind in per_arm[a]]
        data = [[v / (capacity(report, a) or 1) for v in per_arm[a][kind]] for a in names]
        ax.boxplot(data, showfliers=True, widths=0.6)
        ax.set_xticks(range(1, len(names) + 1), names, rotation=35, ha="right", fontsize=7)
        ax.set_title(kind, fontsize=9)
        ax.grid(alpha=0.3, axis="y")
    axes[0][0].set_ylabel("active rank / declared rank")
    axes[0][0].set_ylim(0, 1.05)
    fig.suptitle("Active ranks per module kind (each point: one adapted layer of one run)", fontsize=9)
    return _save(fig, path)


def _layer_ranks(workspace: Workspace, report: StudyReport, arm: str) -> dict[str, list[float]]:
    """Module kind -> the active rank of every adapted layer of every final checkpoint of the arm."""
    kinds: dict[str, list[float]] = {}
    for record in run_summaries(workspace, report.final_checkpoints.get(arm, [])):
        for layer, rank in (record["summary"].get("active_ranks") or {}).items():
            kinds.setdefault(module_kind(f"{layer}.weight"), []).append(float(rank))
    return kinds


def _form_lines(ax: Any, x: dict[str, Any], rows: list[FormRow], annotate: bool) -> list[float]:
    """Each form's variants as points with their 95 % interval, joined in order of x; what is drawn."""
    shown: list[float] = []
    for form in dict.fromkeys(r.form for r in rows):
        mine = sorted((r for r in rows if r.form == form), key=lambda r: x[r.arm])
        ys = [r.endpoint.mean for r in mine]
        low = [r.endpoint.mean - r.endpoint.ci_low for r in mine]
        high = [r.endpoint.ci_high - r.endpoint.mean for r in mine]
        colour = FORM_COLOURS.get(form)
        xs = [x[r.arm] for r in mine]
        ax.errorbar(xs, ys, yerr=[low, high], fmt="o-", color=colour, capsize=3, lw=1.2, ms=5, label=form)
        for r in mine if annotate else []:
            ax.annotate(
                r.arm,
                (x[r.arm], r.endpoint.mean),
                textcoords="offset points",
                xytext=(4, 4),
                fontsize=7,
                color=colour,
            )
        shown += [r.endpoint.ci_low for r in mine] + [r.endpoint.ci_high for r in mine]
    return shown


def _finish(ax: Any, shown: list[float], row: FormRow, xlabel: str, title: str) -> None:
    low, high = y_range(shown)
    ax.set_ylim(low - 2, high)  # a point at 0 % stays visible above the axis
    ax.set_xlabel(xlabel)
    ax.set_ylabel("test success at the endpoint (%)")
    n = row.endpoint
    ax.set_title(f"{title}: mean and 95 % CI ({n.n_seeds} seeds × {n.n_goals} goals)", fontsize=9)
    ax.legend(fontsize=8, frameon=False)
    ax.grid(alpha=0.3, which="both")


def _save(fig: Any, path: Path) -> Path:
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path
