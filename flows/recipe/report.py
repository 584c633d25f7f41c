"""`capvector report` of an old `report` artifact (what `capvector run` wrote until the recipe run once
became a study, capvector.flows.study.recipe): Markdown + PNG figures (comparison, vector, curves). A
reader of records: nothing writes that kind now; a study's report is capvector.flows.study.figures.

Every number in the document names the catalogue id it came from, so `capvector lineage ID` can
trace it back to the data.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from capvector.flows.recipe.config import ARMS, lambda_label  # noqa: E402
from capvector.tasks.runtime.workspace import Workspace  # noqa: E402
from capvector.tasks.steps.reporting import Report, load_report, markdown_table, timings, trained_with  # noqa: E402


def latest_report_id(workspace: Workspace) -> str:
    frame = workspace.api.query(
        "SELECT id FROM artifacts WHERE kind = 'report' ORDER BY created_at DESC LIMIT 1"
    )
    if frame.empty:
        raise ValueError("the catalogue has no report yet: run `capvector run` first (or pass a report id)")
    return str(frame.iloc[0, 0])


def plot_comparison(report: Report, path: Path) -> Path:
    arms = list(report.arms)
    means = [100 * row.overall.mean for row in report.arms.values()]
    stds = [100 * row.overall.std for row in report.arms.values()]
    fig, ax = plt.subplots(figsize=(1.4 * len(arms) + 2, 3.2))
    ax.bar(arms, means, yerr=stds, capsize=4, color="#4c72b0")
    ax.set_ylabel("downstream success (%)")
    ax.set_ylim(0, 100)
    ax.set_title("mean ± std over training seeds")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_vector_stats(rows: list[dict[str, Any]], path: Path) -> Path:
    groups = [r for r in rows if r.get("level") == "group"]
    names = [r["tensor"] for r in groups]
    fig, axes = plt.subplots(1, 2, figsize=(10, 0.28 * len(names) + 1.5))
    axes[0].barh(names, [r["rel_norm"] or 0 for r in groups], color="#55a868")
    axes[0].set_xlabel("‖γ‖ / ‖θ_pt‖ per module group")
    axes[1].barh(names, [r["cosine_ref"] or 0 for r in groups], color="#c44e52")
    axes[1].set_xlabel("cos(γ, θ_ft − θ_pt)")
    axes[1].set_yticklabels([])
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_curves(curves: dict[str, list[dict[str, Any]]], path: Path) -> Path:
    fig, ax = plt.subplots(figsize=(6, 3.2))
    for label, rows in curves.items():
        ax.plot([r["step"] for r in rows], [r.get("action", r.get("loss")) for r in rows], label=label, lw=1)
    ax.set_xlabel("step")
    ax.set_ylabel("action L1 loss")
    ax.set_yscale("log")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _vector_of(workspace: Workspace, report: Report) -> str | None:
    """The capability vector behind this report's runs (merged into, or regularizing, a checkpoint)."""
    for row in report.arms.values():
        for run in row.runs:
            merged = workspace.api.vectors_merged_into(run.checkpoint_id)
            if merged:
                return merged[0].vector_id
    return None


def plot_convergence(points: dict[str, list[tuple[int, float, float]]], path: Path) -> Path:
    fig, ax = plt.subplots(figsize=(6, 3.2))
    for arm, rows in sorted(points.items()):
        rows = sorted(rows)
        ax.errorbar(
            [r[0] for r in rows],
            [100 * r[1] for r in rows],
            yerr=[100 * r[2] for r in rows],
            label=arm,
            marker="o",
            capsize=3,
            lw=1,
        )
    ax.set_xlabel("downstream training steps (budget)")
    ax.set_ylabel("success (%)")
    ax.set_ylim(0, 100)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _trained_with(workspace: Workspace, checkpoint_id: str, key: str) -> Any:
    return trained_with(workspace.api.get(checkpoint_id).config, key)


def _sweep_seed(doc: dict[str, Any]) -> Any:
    """A sweep's training seed: `seed` in one the sweep flow recorded, the tuning `seeds` in one a sweep
    study (`capvector sweep`) records."""
    return doc["seed"] if "seed" in doc else ", ".join(map(str, doc["seeds"]))


def _sweep_section(workspace: Workspace, sweep_id: str, doc: dict[str, Any]) -> str:
    from capvector.flows.study.report import sweep_markdown

    best = doc["best"]
    lr = _trained_with(workspace, best["checkpoint_ids"][0], "lr")
    return (
        f"\n## α × λ sweep `{sweep_id[:12]}` "
        f"(validation goal variations, arm `{doc['arm']}`, seed {_sweep_seed(doc)}"
        f"{f', lr {lr:g}' if lr is not None else ''})\n\n"
        + sweep_markdown(doc)
        + f"\nChosen: α = {best['alpha']}, {lambda_label(best)} (validation success "
        f"{100 * best['validation_success']:.1f}%). Test seeds were not used for the choice.\n"
    )


def _learning_rate_section(workspace: Workspace, cells: list[tuple[str, dict[str, Any]]]) -> str:
    """One-cell sweeps are how a learning rate is chosen: one table, the best lr of each arm marked."""
    rows = []
    for sid, doc in cells:
        lr = _trained_with(workspace, doc["best"]["checkpoint_ids"][0], "lr") or 0.0
        rows.append((doc["arm"], lr, sid, doc["best"], _sweep_seed(doc)))
    rows.sort()
    best = {arm: max(r[3]["validation_success"] for r in rows if r[0] == arm) for arm, *_ in rows}
    lines = [
        "\n## Learning rate, chosen on validation goal variations\n",
        "| arm | lr | α | λ | validation success | seed | sweep |",
        "|---|---|---|---|---|---|---|",
    ]
    for arm, lr, sid, cell, seed in rows:
        mark = " **(best)**" if cell["validation_success"] == best[arm] else ""
        merged = ARMS[arm].init == "meta"  # α and λ mean nothing to an arm that starts from θ_pt
        alpha, lam = (cell["alpha"], lambda_label(cell)) if merged else ("–", "–")
        lines.append(
            f"| {arm} | {lr:g} | {alpha} | {lam} | "
            f"{100 * cell['validation_success']:.1f}%{mark} | {seed} | `{sid[:12]}` |"
        )
    lines.append("\nTest seeds were not used for the choice.\n")
    return "\n".join(lines)


def _figure_path(out: Path, name: str) -> Path:
    """A figure's file beside the Markdown, named after it (`<stem>_<name>.png`)."""
    return out.parent / f"{out.stem}_{name}.png"


def _curves_figure(workspace: Workspace, table: Report, path: Path) -> Path | None:
    """The training curve of each arm's first run, when its checkpoint recorded one."""
    curves = {}
    for arm, row in table.arms.items():
        run = row.runs[0]
        curve = workspace.api.get(run.checkpoint_id).config.get("curve")
        if curve:
            curves[f"{arm} ({run.label})"] = curve
    return plot_curves(curves, path) if curves else None


def _budget_points(
    workspace: Workspace, table: Report, extra: dict[str, Report]
) -> dict[str, list[tuple[int, float, float]]]:
    """Arm -> (downstream steps, mean, std) over the reports that share the comparison's arms and seeds."""
    points: dict[str, list[tuple[int, float, float]]] = {}
    for tab in [table, *extra.values()]:
        for arm, row in tab.arms.items():
            main_row = table.arms.get(arm)
            if main_row is None or row.overall.n != main_row.overall.n:
                continue  # only budget variants of the comparison's own arms and seeds
            steps = _trained_with(workspace, row.runs[0].checkpoint_id, "steps")
            if steps:
                points.setdefault(arm, []).append((steps, row.overall.mean, row.overall.std))
    return points


def _convergence_figure(
    workspace: Workspace, table: Report, extra: dict[str, Report], path: Path
) -> Path | None:
    """Success against steps, only when the reports differ in downstream budget (else it is one point)."""
    points = _budget_points(workspace, table, extra)
    if len({p[0] for rows in points.values() for p in rows}) > 1:
        return plot_convergence(points, path)
    return None


def _introduction(report_id: str, name: str, notes: str | None) -> str:
    """The title and how to read every number: what the rates are over, and that ids trace to the data."""
    return (
        f"# capvector report `{report_id[:12]}` ({name})\n\n"
        "Success rates in %, mean ± std over training seeds, final checkpoints only, test goal variations "
        "(evaluation seeds, disjoint from demonstration and validation seeds). Every id is a catalogue id: "
        "`capvector lineage ID` traces it to its data.\n\n" + (notes + "\n\n" if notes else "")
    )


def _comparison_section(workspace: Workspace, table: Report, figure: Path) -> str:
    """The comparison table rendered here, with the measured speeds from the training records: a report's
    content (its id) holds only what its checkpoints and scores determine, so its own `markdown` has no
    timings."""
    main_table = markdown_table(table, timings(workspace, table))
    return f"## Comparison\n\n{main_table}\n![comparison]({figure.name})\n"


def _extra_section(workspace: Workspace, title: str, report_id: str, tab: Report) -> str:
    text = markdown_table(tab, timings(workspace, tab))
    return f"\n## {title} (`{report_id[:12]}`)\n\n{text}"


def _convergence_section(figure: Path | None) -> str:
    if figure is None:
        return ""
    return f"\n## Success against training steps\n\n![convergence]({figure.name})\n"


def _sweeps_sections(workspace: Workspace, sweep_ids: list[str]) -> str:
    """Each α × λ grid in full, then the one-cell sweeps (how a learning rate is chosen) in one table."""
    unique_ids = dict.fromkeys(sweep_ids)  # a repeated id is shown once
    sweeps = [(sid, workspace.api.store.open_json(workspace.api.get(sid).id)) for sid in unique_ids]
    parts = [_sweep_section(workspace, sid, doc) for sid, doc in sweeps if len(doc["grid"]) > 1]
    cells = [(sid, doc) for sid, doc in sweeps if len(doc["grid"]) == 1]
    if cells:
        parts.append(_learning_rate_section(workspace, cells))
    return "".join(parts)


def _vector_section(workspace: Workspace, table: Report, path: Path) -> str:
    """γ's size and direction with its figure, when the catalogue holds statistics of the runs' vector."""
    vector_id = _vector_of(workspace, table)
    stats = workspace.api.query("SELECT DISTINCT stats_id FROM vector_stats WHERE vector_id = ?", [vector_id])
    if not vector_id or stats.empty:
        return ""
    stats_id = str(stats.iloc[0, 0])
    rows = workspace.api.store.open_json(stats_id)["tensors"]
    figure = plot_vector_stats(rows, path)
    overall = next((r for r in rows if r.get("level") == "all"), None)
    if not overall:
        return ""
    return (
        f"\n## Capability vector γ `{vector_id[:12]}`\n\n"
        f"‖γ‖ = {overall['l2']:.4g}, ‖γ‖/‖θ_pt‖ = {overall['rel_norm'] or 0:.3g}, "
        f"cos(γ, θ_ft − θ_pt) = {overall['cosine_ref'] or 0:.3f}, "
        f"sign agreement {overall['sign_agreement'] or 0:.3f} (statistics `{stats_id[:12]}`).\n\n"
        f"![vector]({figure.name})\n"
    )


def _curves_section(figure: Path | None) -> str:
    return f"\n## Training curves\n\n![curves]({figure.name})\n" if figure is not None else ""


def _runs_section(tables: list[Report]) -> str:
    """Every run with its checkpoint and evaluation ids, so each mean above can be traced to its runs."""
    runs = ["| run | checkpoint | evaluation | success |", "|---|---|---|---|"]
    for tab in tables:
        for row in tab.arms.values():
            for run in row.runs:
                runs.append(
                    f"| {run.label} | `{run.checkpoint_id[:12]}` | `{run.evaluation_id[:12]}` | "
                    f"{100 * run.mean_success:.1f}% |"
                )
    return "\n## Runs\n\n" + "\n".join(runs) + "\n"


def write_report(
    workspace: Workspace,
    report_id: str,
    out: Path,
    sections: dict[str, str] | None = None,
    sweep_ids: list[str] | None = None,
    notes: str | None = None,
) -> Path:
    """Write `out` (Markdown) and its figures beside it; returns the Markdown path.

    `sections`: title -> another report id (ablations, other budgets), shown as extra tables; when
    the reports differ in downstream budget, a success-vs-steps figure is drawn from all of them.
    `sweep_ids`: sweeps shown after the tables: each α × λ grid in full, and the one-cell sweeps (how a
    learning rate is chosen) gathered into one table.
    """
    record = workspace.api.get(report_id)
    table = load_report(workspace, record.id)
    out.parent.mkdir(parents=True, exist_ok=True)
    comparison = plot_comparison(table, _figure_path(out, "comparison"))
    extra = {title: load_report(workspace, rid) for title, rid in (sections or {}).items()}
    curves = _curves_figure(workspace, table, _figure_path(out, "curves"))
    convergence = _convergence_figure(workspace, table, extra, _figure_path(out, "convergence"))
    vector = _vector_section(workspace, table, _figure_path(out, "vector"))
    parts = [
        _introduction(record.id, record.name, notes),
        _comparison_section(workspace, table, comparison),
        *(_extra_section(workspace, title, (sections or {})[title], tab) for title, tab in extra.items()),
        _convergence_section(convergence),
        _sweeps_sections(workspace, sweep_ids or []),
        vector,
        _curves_section(curves),
        _runs_section([table, *extra.values()]),
    ]
    out.write_text("".join(parts))
    return out
