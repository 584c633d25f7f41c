"""Step: the comparison table of the pipeline's arms (mean ± std over training seeds, per task)."""

from __future__ import annotations

import statistics
from typing import Any

from pydantic import BaseModel

from capvector.artifacts.scores import read_scores
from capvector.tasks.runtime.step_kinds import StepCall, StepKind, step_task
from capvector.tasks.runtime.workspace import Workspace, provenance


class MeanStd(BaseModel):
    """A score over an arm's training seeds."""

    mean: float
    std: float
    n: int

    @classmethod
    def of(cls, values: list[float]) -> MeanStd:
        return cls(
            mean=statistics.fmean(values),
            std=statistics.stdev(values) if len(values) > 1 else 0.0,
            n=len(values),
        )

    def pct(self) -> str:
        return f"{100 * self.mean:.1f} ± {100 * self.std:.1f}"


class ReportRun(BaseModel):
    """One training seed of an arm: its checkpoint, its evaluation and that evaluation's scores."""

    label: str
    evaluation_id: str
    checkpoint_id: str
    success_rates: dict[str, float]
    mean_success: float
    trainable_parameters: int | None = None
    lr: float | None = None
    active_ranks: dict[str, float] | None = None


class ArmRow(BaseModel):
    overall: MeanStd
    per_task: dict[str, MeanStd]
    trainable_parameters: int | None = None
    lr: float | None = None
    runs: list[ReportRun]


class Report(BaseModel):
    """Content of a `kind="report"` artifact: written and read through this model only."""

    fingerprint: str | None
    arms: dict[str, ArmRow]
    markdown: str = ""


def load_report(workspace: Workspace, report_id: str) -> Report:
    return Report.model_validate(workspace.api.store.open_json(workspace.api.get(report_id).id))


def trained_with(checkpoint_config: dict[str, Any], key: str) -> Any:
    """A setting of the training run that made a checkpoint (`lr`, `steps`, ...); None if unrecorded."""
    return checkpoint_config.get("train_step", {}).get("train", {}).get(key)


def comparison(workspace: Workspace, evaluations: dict[str, str]) -> Report:
    """`evaluations`: label "<arm>/seed<k>" -> evaluation id (full). Refuses mixed protocols.

    This is the report's content, so its id: only what the evaluated checkpoints and their scores
    determine. Scores come from the catalogue (capvector.artifacts.scores), never from a sidecar. Measured
    speeds and wall times differ from one run, machine or load to the next, so they stay in the checkpoints'
    records (sidecars) and are read from there when a report is rendered (`timings`, `markdown_table(report,
    timings)`).
    """
    scores = {s.evaluation_id: s for s in read_scores(workspace.api, evaluations=evaluations.values())}
    per_arm: dict[str, list[ReportRun]] = {}
    for label, eval_id in sorted(evaluations.items()):
        score = scores[eval_id]
        checkpoint = workspace.api.get(score.checkpoint_id)
        summary = checkpoint.config.get("summary", {})
        per_arm.setdefault(label.split("/")[0], []).append(
            ReportRun(
                label=label,
                evaluation_id=eval_id,
                checkpoint_id=checkpoint.id,
                success_rates=score.success_rates,
                mean_success=score.mean_success,
                trainable_parameters=summary.get("trainable_parameters"),
                lr=trained_with(checkpoint.config, "lr"),
                active_ranks=summary.get("active_ranks"),
            )
        )
    fingerprints = {s.fingerprint for s in scores.values()}
    if len(fingerprints) > 1:
        raise ValueError(f"evaluations use {len(fingerprints)} different protocols; refusing to compare them")
    arms = {}
    for arm, runs in per_arm.items():
        tasks = sorted(runs[0].success_rates)
        arms[arm] = ArmRow(
            overall=MeanStd.of([r.mean_success for r in runs]),
            per_task={t: MeanStd.of([r.success_rates[t] for r in runs]) for t in tasks},
            trainable_parameters=runs[0].trainable_parameters,
            lr=runs[0].lr,
            runs=runs,
        )
    return Report(fingerprint=fingerprints.pop() if fingerprints else None, arms=arms)


def timings(workspace: Workspace, report: Report) -> dict[str, dict[str, float | None]]:
    """arm -> `ms_per_step` and `train_wall_s`, medians over the arm's runs, from the training records
    (the checkpoints' sidecars): provenance, kept out of the report's content.

    Medians: a seed's checkpoint may be a cache hit trained under other load (a sweep cell)."""
    out = {}
    for arm, row in report.arms.items():
        speeds, walls = [], []
        for run in row.runs:
            summary = workspace.api.get(run.checkpoint_id).config.get("summary", {})
            speed, steps = summary.get("steps_per_s"), summary.get("steps")
            if speed:
                speeds.append(speed)
                if steps:
                    walls.append(steps / speed)
        out[arm] = {
            "ms_per_step": 1000.0 / statistics.median(speeds) if speeds else None,
            "train_wall_s": statistics.median(walls) if walls else None,
        }
    return out


def markdown_table(report: Report, timings: dict[str, dict[str, float | None]] | None = None) -> str:
    """The comparison as Markdown; with `timings` (see `timings`), two columns of measured speed."""
    if not report.arms:
        return "(no evaluations)\n"
    tasks = sorted(next(iter(report.arms.values())).per_task)
    measured = ["ms/step (median)", "training s (median)"] if timings is not None else []
    head = ["arm", "overall", *tasks, *measured, "trainable params", "lr", "seeds"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for arm, row in report.arms.items():
        cells = [arm, row.overall.pct()] + [row.per_task[t].pct() for t in tasks]
        if timings is not None:
            ms, wall = (timings.get(arm, {}).get(k) for k in ("ms_per_step", "train_wall_s"))
            cells += [f"{ms:.1f}" if ms else "-", f"{wall:.0f}" if wall else "-"]
        cells += [f"{row.trainable_parameters or '-'}", f"{row.lr:g}" if row.lr else "-", str(row.overall.n)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + f"\n\nProtocol fingerprint: `{report.fingerprint}`\n"


def _report(call: StepCall) -> str:
    report = comparison(call.workspace, call.inputs)
    report.markdown = markdown_table(report)
    record = call.workspace.api.register_json(
        report,
        kind="report",
        name=call.step,
        config={**call.config, "cache_key": call.key},
        parents=[(eval_id, "evaluation") for eval_id in dict.fromkeys(call.inputs.values())],
        **provenance(),
    )
    return record.id


REPORT = StepKind("report", None, (), _report)
run_report = REPORT.run
report_task = step_task(REPORT)
