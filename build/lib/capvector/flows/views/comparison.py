"""`capvector compare`: latest per-task scores of several checkpoints under one protocol."""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel

from capvector.artifacts.scores import EvaluationScores, read_scores
from capvector.tasks.runtime.workspace import Workspace


class ComparedCheckpoint(BaseModel):
    checkpoint_id: str
    name: str
    evaluation_id: str
    success_rates: dict[str, float]
    mean: float


class CheckpointComparison(BaseModel):
    fingerprint: str
    rows: list[ComparedCheckpoint]


def compare_checkpoints(
    workspace: Workspace, checkpoints: list[str], fingerprint: str | None
) -> CheckpointComparison:
    """Each checkpoint's latest evaluation under one protocol. Refuses to mix protocols: without
    `fingerprint` (a prefix is enough), the checkpoints must share exactly one."""
    ids = list(dict.fromkeys(workspace.api.get(c).id for c in checkpoints))
    scores = read_scores(workspace.api, checkpoints=ids)
    if not scores:
        raise ValueError("none of these checkpoints has an evaluation; run `capvector evaluate` first")
    if fingerprint is None:
        shared = set.intersection(*[{s.fingerprint for s in scores if s.checkpoint_id == c} for c in ids])
        if len(shared) != 1:
            raise ValueError(
                f"the checkpoints share {len(shared)} evaluation protocols {sorted(x[:12] for x in shared)}; "
                "pass --fingerprint to choose one (scores under different protocols are never compared)"
            )
        fingerprint = shared.pop()
    latest: dict[str, EvaluationScores] = {}
    for s in scores:  # oldest first: the last one of a checkpoint wins
        if s.fingerprint.startswith(fingerprint):
            latest[s.checkpoint_id] = s
    protocols = {s.fingerprint for s in latest.values()}
    if len(protocols) > 1:
        raise ValueError(f"--fingerprint {fingerprint!r} matches {len(protocols)} protocols; give more of it")
    missing = [c[:12] for c in ids if c not in latest]
    if missing:
        raise ValueError(f"no evaluation under protocol {fingerprint[:12]} for {', '.join(missing)}")
    rows = [
        ComparedCheckpoint(
            checkpoint_id=cid,
            name=workspace.api.get(cid).name,
            evaluation_id=latest[cid].evaluation_id,
            success_rates=latest[cid].success_rates,
            mean=latest[cid].mean_success,
        )
        for cid in ids
    ]
    return CheckpointComparison(fingerprint=protocols.pop(), rows=rows)


def plot_compare(result: CheckpointComparison, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = sorted({t for r in result.rows for t in r.success_rates})
    width = 0.8 / max(len(result.rows), 1)
    fig, ax = plt.subplots(figsize=(max(4, 1.5 * len(tasks) + 2), 3.2))
    for i, row in enumerate(result.rows):
        xs = [j + i * width for j in range(len(tasks))]
        ax.bar(
            xs,
            [100 * row.success_rates.get(t, 0) for t in tasks],
            width,
            label=f"{row.name} {row.checkpoint_id[:8]}",
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
