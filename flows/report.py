"""`capvector report`: Markdown + PNG figures of a pipeline report (comparison, vector, curves).

Every number in the document names the catalogue id it came from, so `capvector lineage ID` can
trace it back to the data.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from tasks.workspace import Workspace  # noqa: E402


def latest_report_id(workspace: Workspace) -> str:
    frame = workspace.api.query(
        "SELECT id FROM artifacts WHERE kind = 'report' ORDER BY created_at DESC LIMIT 1"
    )
    if frame.empty:
        raise ValueError("the catalogue has no report yet: run `capvector run` first (or pass a report id)")
    return str(frame.iloc[0, 0])


def plot_comparison(table: dict[str, Any], path: Path) -> Path:
    arms = list(table["arms"])
    means = [100 * table["arms"][a]["overall"]["mean"] for a in arms]
    stds = [100 * table["arms"][a]["overall"]["std"] for a in arms]
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


def write_report(workspace: Workspace, report_id: str, out: Path) -> Path:
    """Write `out` (Markdown) and its figures beside it; returns the Markdown path."""
    record = workspace.api.get(report_id)
    table = workspace.api.store.open_json(record.id)
    out.parent.mkdir(parents=True, exist_ok=True)
    stem = out.stem
    figures = {"comparison": plot_comparison(table, out.parent / f"{stem}_comparison.png")}

    curves = {}
    for arm, row in table["arms"].items():
        run = row["runs"][0]
        curve = workspace.api.get(run["checkpoint_id"]).config.get("curve")
        if curve:
            curves[f"{arm} ({run['label']})"] = curve
    if curves:
        figures["curves"] = plot_curves(curves, out.parent / f"{stem}_curves.png")

    vector_section = ""
    checkpoint = next(iter(table["arms"].values()))["runs"][0]["checkpoint_id"] if table["arms"] else None
    vectors = workspace.api.query(
        "SELECT DISTINCT vector_id, stats_id FROM vector_stats WHERE vector_id IN "
        "(SELECT parent FROM edges WHERE role IN ('vector', 'regularized_by'))"
    )
    if not vectors.empty and checkpoint:
        vector_id, stats_id = str(vectors.iloc[0, 0]), str(vectors.iloc[0, 1])
        rows = workspace.api.store.open_json(stats_id)["tensors"]
        figures["vector"] = plot_vector_stats(rows, out.parent / f"{stem}_vector.png")
        overall = next((r for r in rows if r.get("level") == "all"), None)
        if overall:
            vector_section = (
                f"\n## Capability vector γ `{vector_id[:12]}`\n\n"
                f"‖γ‖ = {overall['l2']:.4g}, ‖γ‖/‖θ_pt‖ = {overall['rel_norm'] or 0:.3g}, "
                f"cos(γ, θ_ft − θ_pt) = {overall['cosine_ref'] or 0:.3f}, "
                f"sign agreement {overall['sign_agreement'] or 0:.3f} (statistics `{stats_id[:12]}`).\n\n"
                f"![vector]({figures['vector'].name})\n"
            )

    runs = ["| run | checkpoint | evaluation | success |", "|---|---|---|---|"]
    for row in table["arms"].values():
        for run in row["runs"]:
            runs.append(
                f"| {run['label']} | `{run['checkpoint_id'][:12]}` | `{run['evaluation_id'][:12]}` | "
                f"{100 * run['mean_success']:.1f}% |"
            )
    text = (
        f"# capvector report `{record.id[:12]}` ({record.name})\n\n"
        "Success rates in %, mean ± std over training seeds, final checkpoints only, "
        "test goal variations.\n\n"
        f"{table['markdown']}\n![comparison]({figures['comparison'].name})\n\n"
        f"## Runs\n\n"
        + "\n".join(runs)
        + "\n"
        + vector_section
        + (f"\n## Training curves\n\n![curves]({figures['curves'].name})\n" if "curves" in figures else "")
    )
    out.write_text(text)
    return out
