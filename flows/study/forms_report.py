"""The report's section on fine-tuning forms (a study with `study.variants`, issue 40's rank study).

One row per arm: its form and setting, the lr chosen for it, success at each budget and at the primary
endpoint with 95 % intervals, the paired difference against full fine-tuning, trainable parameters, wall
time per training step and, for the rank-adaptive forms (LoRA-SP, AdaLoRA), the active ranks per module
kind. Parameters, speed and ranks come from the final checkpoints' run summaries (`trainable_parameters`,
`steps_per_s`, `active_ranks`), never from the analysed document, whose id depends on results only.
Then each form's spread over its variants ("robust to rank", capvector.tasks.steps.study_forms).
"""

from __future__ import annotations

import statistics
from typing import Any

from pydantic import BaseModel

from capvector.core.vectors.spectrum import KIND_ORDER, module_kind
from capvector.stats.paired_differences import Comparison, CurvePoint
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.steps.study_analysis import StudyReport

FORM_NAMES = {"sft": "full", "sft_lora": "LoRA", "sft_lora_sp": "LoRA-SP", "sft_adalora": "AdaLoRA"}
KIND_NAMES = {"attention": "attn", "mlp": "MLP", "action_head": "head", "encoder": "enc", "other": "other"}


class FormRow(BaseModel):
    """One arm of a study of fine-tuning forms, as the table and the figure show it."""

    arm: str
    form: str
    setting: str
    lr: float | None
    budgets: dict[int, CurvePoint]
    endpoint: CurvePoint | None
    vs_full: Comparison | None
    trainable_parameters: float | None
    seconds_per_step: float | None
    active_ranks: dict[str, float]
    """Module kind -> mean active rank over its adapted layers and the arm's runs (rank-adaptive forms)."""


def run_summaries(workspace: Workspace, ids: list[str]) -> list[dict[str, Any]]:
    return [workspace.api.get(i).config or {} for i in ids]


def ranks_by_kind(active: dict[str, float]) -> dict[str, float]:
    """A run's active rank per layer -> the mean per module kind (capvector.core.vectors.spectrum)."""
    kinds: dict[str, list[float]] = {}
    for layer, rank in active.items():
        kinds.setdefault(module_kind(f"{layer}.weight"), []).append(float(rank))
    return {k: statistics.fmean(kinds[k]) for k in KIND_ORDER if k in kinds}


def _median(values: list[Any]) -> float | None:
    values = [v for v in values if v]
    return float(statistics.median(values)) if values else None


def _mean_ranks(records: list[dict[str, Any]]) -> dict[str, float]:
    per_run = [
        ranks_by_kind(r["summary"]["active_ranks"]) for r in records if r["summary"].get("active_ranks")
    ]
    kinds = [k for k in KIND_ORDER if any(k in run for run in per_run)]
    return {k: statistics.fmean(run[k] for run in per_run if k in run) for k in kinds}


def form_rows(workspace: Workspace, report: StudyReport) -> list[FormRow]:
    """Full fine-tuning first, then each variant in its declared order."""
    variants = report.design.variants
    rows = []
    for arm in ["sft", *variants]:
        records = run_summaries(workspace, report.final_checkpoints.get(arm, []))
        speeds = _median([r["summary"].get("steps_per_s") for r in records])
        declared = variants.get(arm, {"arm": "sft", "set": {}})
        setting = ", ".join(f"{k}={v}" for k, v in declared["set"].items()) or "all weights"
        lrs = {r["train_step"]["train"]["lr"] for r in records}
        rows.append(
            FormRow(
                arm=arm,
                form=FORM_NAMES.get(declared["arm"], declared["arm"]),
                setting=setting,
                lr=lrs.pop() if len(lrs) == 1 else None,
                budgets={p.budget: p for p in report.curves.get(arm, [])},
                endpoint=report.endpoints.get(arm),
                vs_full=report.comparison(arm, "sft"),
                trainable_parameters=_median([r["summary"].get("trainable_parameters") for r in records]),
                seconds_per_step=1.0 / speeds if speeds else None,
                active_ranks=_mean_ranks(records),
            )
        )
    return rows


def _point(p: CurvePoint | None) -> str:
    return "—" if p is None else f"{p.mean:.1f} [{p.ci_low:.1f}, {p.ci_high:.1f}]"


def _difference(c: Comparison | None) -> str:
    if c is None:
        return "—"
    flag = "" if c.reliable else " (df < 2: not readable)"
    return f"{c.difference:+.1f} [{c.ci_low:+.1f}, {c.ci_high:+.1f}]{flag}"


def _ranks(ranks: dict[str, float]) -> str:
    return ", ".join(f"{KIND_NAMES.get(k, k)} {v:.1f}" for k, v in ranks.items()) or "—"


def _table(rows: list[FormRow], budgets: list[int]) -> list[str]:
    head = " | ".join(f"@ {b}" for b in budgets)
    lines = [
        f"| arm | form | setting | lr | {head} | endpoint | − full FT | trainable params | s/step | "
        "active ranks |",
        "|---|---|---|---|" + "---|" * len(budgets) + "---|---|---|---|---|",
    ]
    for r in rows:
        cells = " | ".join(_point(r.budgets.get(b)) for b in budgets)
        params = f"{r.trainable_parameters:,.0f}" if r.trainable_parameters else "—"
        sec = f"{r.seconds_per_step:.4f}" if r.seconds_per_step else "—"
        lr = f"{r.lr:g}" if r.lr else "—"
        diff = "(baseline)" if r.arm == "sft" else _difference(r.vs_full)
        lines.append(
            f"| {r.arm} | {r.form} | {r.setting} | {lr} | {cells} | {_point(r.endpoint)} | {diff} | "
            f"{params} | {sec} | {_ranks(r.active_ranks)} |"
        )
    return lines


def _spreads(report: StudyReport) -> list[str]:
    if not report.rank_spread:
        return []
    lines = [
        "",
        "Robust to rank: each form's spread over its variants at the endpoint, max − min of their endpoint "
        "means, with the 95 % interval of the paired difference best − worst (mean ± t_df·√V̂, paired by seed "
        "and goal). Best and worst are read from the same data, so variants that truly tie still give a "
        "spread above 0 on average: an interval well above 0 says capacity matters for that form; one that "
        "includes 0 says this design saw no dependence on it, not that there is none.",
        "",
        "| form | variants | best | worst | spread [95 % CI] | MDD |",
        "|---|---|---|---|---|---|",
    ]
    for s in report.rank_spread:
        c = s.comparison
        lines.append(
            f"| {FORM_NAMES.get(s.form, s.form)} | {', '.join(s.variants)} | {s.best} | {s.worst} | "
            f"{_difference(c)} | {c.mdd:.1f} |"
        )
    return lines


def forms_section(workspace: Workspace, report: StudyReport) -> list[str]:
    """The section ([] for a study without variants)."""
    if not report.design.variants:
        return []
    budgets = sorted({b for points in report.curves.values() for p in points if (b := p.budget) > 0})
    return [
        "",
        "## Fine-tuning forms (success %, mean [95 % CI])",
        "",
        "Every arm starts from θ_pt and fine-tunes on the downstream tasks together; each variant's lr is "
        "chosen from its grid on validation goals at the tuning seeds, at the endpoint. − full FT: the "
        "paired difference with full fine-tuning at the endpoint. Trainable parameters, time per step "
        "(median over runs) and active ranks (mean per adapted layer of each module kind, over runs) "
        "come from the runs' summaries.",
        "",
        *_table(form_rows(workspace, report), budgets),
        *_declared(report),
        *_spreads(report),
    ]


def _declared(report: StudyReport) -> list[str]:
    """The pairs the study declared besides each variant against full FT (`study.compare`)."""
    if not report.design.compare:
        return []
    lines = ["", "Declared comparisons at the endpoint (paired by seed and goal):", "",
             "| comparison | difference [95 % CI] | MDD |", "|---|---|---|"]  # fmt: skip
    for arm, baseline in report.design.compare:
        c = report.comparison(arm, baseline)
        lines.append(f"| {arm} − {baseline} | {_difference(c)} | {f'{c.mdd:.1f}' if c else '—'} |")
    return lines
