"""A study's report as files: Markdown and its PNG figures, written side by side.

Three figures, drawn from the `study` artifact alone: success vs downstream steps per arm with 95 %
bands (budget 0 is the checkpoint a run starts from), a forest plot of the paired differences at the
primary endpoint with each comparison's MDD marked, and the endpoint per task and arm.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from capvector_stats.paired_differences import ENDPOINT  # noqa: E402
from flows.study_markdown import NAMES, load_study_report, study_markdown  # noqa: E402
from tasks.evaluation import videos_of  # noqa: E402
from tasks.study_analysis import StudyReport  # noqa: E402
from tasks.workspace import Workspace  # noqa: E402

COLOURS = {
    "sft": "#4c72b0",
    "aux": "#dd8452",
    "capvector": "#c44e52",
    "meta_sft": "#8172b3",
    "null_capvector": "#937860",
    "sft_from_ao": "#55a868",
    "sft_from_ft": "#8c8c8c",
}


def plot_curves(report: StudyReport, path: Path) -> Path:
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    for arm, points in report.curves.items():
        steps = [p.budget for p in points]
        colour = COLOURS.get(arm)
        ax.plot(steps, [p.mean for p in points], marker="o", label=NAMES.get(arm, arm), color=colour)
        ax.fill_between(
            steps, [p.ci_low for p in points], [p.ci_high for p in points], alpha=0.15, color=colour
        )
    ax.set_xlabel("downstream training steps (0: the starting checkpoint)")
    ax.set_ylabel("test success (%)")
    ax.set_ylim(0, 100)
    ax.set_title("Success vs steps, mean and 95 % CI over draws, seeds and goals", fontsize=10)
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
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


def plot_per_task(report: StudyReport, path: Path) -> Path | None:
    if not report.per_task:
        return None
    arms = list(report.per_task)
    tasks = report.tasks
    width = 0.8 / len(arms)
    fig, ax = plt.subplots(figsize=(max(6.4, 0.9 * len(tasks) + 1.5), 3.8))
    for i, arm in enumerate(arms):
        xs = [t + (i - (len(arms) - 1) / 2) * width for t in range(len(tasks))]
        values = [report.per_task[arm].get(task, 0.0) for task in tasks]
        ax.bar(xs, values, width, label=NAMES.get(arm, arm), color=COLOURS.get(arm))
    ax.set_xticks(
        range(len(tasks)), [t.removesuffix("-v3") for t in tasks], rotation=30, ha="right", fontsize=8
    )
    ax.set_ylabel("success at the endpoint (%)")
    ax.set_ylim(0, 100)
    ax.set_title("Per task: mean success over the endpoint's budgets", fontsize=10)
    ax.legend(fontsize=7, ncol=min(4, len(arms)), loc="upper center", bbox_to_anchor=(0.5, -0.3))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def latest_study_id(workspace: Workspace) -> str | None:
    _, rows = workspace.api.query_rows(
        "SELECT id FROM artifacts WHERE kind = 'study' ORDER BY created_at DESC LIMIT 1"
    )
    return str(rows[0][0]) if rows else None


def default_report_path(workspace: Workspace, study_id: str) -> Path:
    """Reports go into the home (`reports/`), never over a tracked file of the directory run from."""
    name = workspace.api.get(study_id).name.removeprefix("analyse study ").replace(" ", "-")
    return Path(workspace.home) / "reports" / f"{name}-{study_id[:12]}.md"


def write_study_report(workspace: Workspace, study_id: str, out: Path) -> Path:
    """`out` (Markdown) and its figures `<stem>_*.png` beside it; returns the Markdown path."""
    report = load_study_report(workspace, study_id)
    out.parent.mkdir(parents=True, exist_ok=True)
    drawn = {
        "Success vs downstream steps": plot_curves(report, out.parent / f"{out.stem}_curves.png"),
        "Paired differences at the endpoint": plot_forest(report, out.parent / f"{out.stem}_forest.png"),
        "Per task": plot_per_task(report, out.parent / f"{out.stem}_tasks.png"),
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
