"""`capvector compare`: latest per-task scores of several checkpoints under one protocol."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from tasks.workspace import Workspace


def compare_checkpoints(
    workspace: Workspace, checkpoints: list[str], fingerprint: str | None
) -> dict[str, Any]:
    """Refuses to mix protocols: without `fingerprint`, the checkpoints must share exactly one."""
    ids = [workspace.api.get(c).id for c in checkpoints]
    marks = ",".join("?" * len(ids))
    frame = workspace.api.query(
        f"SELECT checkpoint_id, task, success_rate, fingerprint, evaluated_at FROM eval_tasks "
        f"WHERE checkpoint_id IN ({marks}) ORDER BY evaluated_at",
        ids,
    )
    if frame.empty:
        raise ValueError("none of these checkpoints has an evaluation; run `capvector evaluate` first")
    if fingerprint is None:
        shared = set.intersection(*[set(frame[frame.checkpoint_id == c].fingerprint) for c in ids])
        if len(shared) != 1:
            raise ValueError(
                f"the checkpoints share {len(shared)} evaluation protocols {sorted(x[:12] for x in shared)}; "
                "pass --fingerprint to choose one (scores under different protocols are never compared)"
            )
        fingerprint = shared.pop()
    frame = frame[frame.fingerprint.str.startswith(fingerprint)]
    rows = []
    for cid in ids:
        latest = frame[frame.checkpoint_id == cid].groupby("task").last()
        rates = {str(t): float(r) for t, r in latest.success_rate.items()}
        rows.append(
            {
                "checkpoint_id": cid,
                "name": workspace.api.get(cid).name,
                "success_rates": rates,
                "mean": sum(rates.values()) / max(len(rates), 1),
            }
        )
    return {"fingerprint": str(frame.fingerprint.iloc[0]), "rows": rows}


def plot_compare(result: dict[str, Any], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = sorted({t for r in result["rows"] for t in r["success_rates"]})
    width = 0.8 / max(len(result["rows"]), 1)
    fig, ax = plt.subplots(figsize=(max(4, 1.5 * len(tasks) + 2), 3.2))
    for i, row in enumerate(result["rows"]):
        xs = [j + i * width for j in range(len(tasks))]
        ax.bar(
            xs,
            [100 * row["success_rates"].get(t, 0) for t in tasks],
            width,
            label=f"{row['name']} {row['checkpoint_id'][:8]}",
        )
    ax.set_xticks([j + 0.4 - width / 2 for j in range(len(tasks))], tasks, rotation=20, fontsize=7)
    ax.set_ylabel("success (%)")
    ax.set_ylim(0, 100)
    ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
