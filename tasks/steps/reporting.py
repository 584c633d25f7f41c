"""Old `report` artifacts, read as records: the comparison table of a pipeline run's arms (mean ± std
over training seeds, per task) that `capvector run` wrote until the recipe run once became a study
(capvector.flows.study.recipe). Nothing writes them now; `capvector report ID` renders them
(capvector.flows.recipe.report)."""

from __future__ import annotations

import statistics
from typing import Any

from pydantic import BaseModel

from capvector.tasks.runtime.workspace import Workspace


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
    """Content of a `kind="report"` artifact: read through this model only."""

    fingerprint: str | None
    arms: dict[str, ArmRow]
    markdown: str = ""


def load_report(workspace: Workspace, report_id: str) -> Report:
    return Report.model_validate(workspace.api.store.open_json(workspace.api.get(report_id).id))


def trained_with(checkpoint_config: dict[str, Any], key: str) -> Any:
    """A setting of the training run that made a checkpoint (`lr`, `steps`, ...); None if unrecorded."""
    return checkpoint_config.get("train_step", {}).get("train", {}).get(key)


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
