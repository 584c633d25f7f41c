"""The `evaluate` and `reevaluate` flows: score any checkpoints, or re-score what a query selects."""

from __future__ import annotations

from typing import Any

from prefect import flow

from capvector.artifacts.scores import read_scores
from capvector.core.evaluation.rollouts import EvalConfig
from capvector.flows.runtime.run_records import publish_markdown, recorded_run, run_name
from capvector.flows.runtime.step_submission import StepRunner, resolve
from capvector.tasks.runtime.workspace import Workspace, workspace_for
from capvector.tasks.steps.evaluation import evaluate_task, reevaluate_task

# Checkpoints with at least one evaluation, and the protocols they were evaluated under.
DEFAULT_SELECTION = "SELECT DISTINCT checkpoint_id FROM eval_tasks"


@flow(name="evaluate", flow_run_name=run_name, log_prints=True, persist_result=False)
def evaluate_flow(home: str, checkpoint_ids: list[str], config: dict[str, Any]) -> dict[str, str]:
    """Evaluate each checkpoint under one protocol (cached: the same checkpoint and protocol run once)."""
    workspace = workspace_for(home)
    eval_config = EvalConfig.model_validate(config).model_dump(mode="json")
    full_ids = [workspace.api.get(i).id for i in checkpoint_ids]  # unknown ids fail before any work
    with recorded_run(workspace, "evaluate", {"checkpoints": full_ids, "config": eval_config}):
        steps = StepRunner(home, len(full_ids), "evaluate")
        futures = {
            cid: steps.submit(evaluate_task, f"evaluate {cid[:12]}", {"checkpoint": cid}, eval_config)
            for cid in full_ids
        }
        return {cid: resolve(f) for cid, f in futures.items()}


def _previous_protocols(workspace: Workspace, checkpoint_id: str) -> list[dict[str, Any]]:
    """The distinct eval configs this checkpoint was evaluated with (from the evaluation records)."""
    frame = workspace.api.query(
        "SELECT DISTINCT evaluation_id FROM eval_tasks WHERE checkpoint_id = ?", [checkpoint_id]
    )
    configs: dict[str, dict[str, Any]] = {}
    for eval_id in frame["evaluation_id"]:
        config = workspace.api.get(eval_id).config.get("eval")
        if config:
            configs[EvalConfig.model_validate(config).model_dump_json()] = config
    return list(configs.values())


def _latest_scores(workspace: Workspace, checkpoint_id: str) -> dict[str, dict[str, float]]:
    """fingerprint -> {task: success rate} of the checkpoint's latest evaluation under that protocol."""
    return {s.fingerprint: s.success_rates for s in read_scores(workspace.api, checkpoints=[checkpoint_id])}


@flow(name="reevaluate", flow_run_name=run_name, log_prints=True, persist_result=False)
def reevaluate_flow(home: str, selection_sql: str = DEFAULT_SELECTION) -> list[dict[str, Any]]:
    """Re-run every (checkpoint, protocol) the selection yields under the installed library versions.

    Evaluations are never overwritten: one whose episodes and library versions differ is a new artifact
    beside the old; one that reproduces them exactly is the same artifact (content-addressed, same id).
    The summary lists, per checkpoint and task, the previous and the new success rate under the same
    protocol fingerprint (the previous ones read before anything ran).
    """
    workspace = workspace_for(home)
    selected = workspace.api.query(selection_sql)
    if selected.empty:
        return []
    checkpoint_ids = [str(x) for x in selected.iloc[:, 0].dropna().unique()]
    with recorded_run(
        workspace, "reevaluate", {"selection_sql": selection_sql, "checkpoints": checkpoint_ids}
    ):
        previous = {cid: _latest_scores(workspace, cid) for cid in checkpoint_ids}
        jobs = [(cid, cfg) for cid in checkpoint_ids for cfg in _previous_protocols(workspace, cid)]
        steps = StepRunner(home, len(jobs), "reevaluate")  # how every flow submits (untagged, placed)
        futures = [
            (cid, steps.submit(reevaluate_task, f"reevaluate {cid[:12]}", {"checkpoint": cid}, cfg))
            for cid, cfg in jobs
        ]
        changes = []
        for cid, future in futures:
            eval_id = resolve(future)
            (scores,) = read_scores(workspace.api, evaluations=[eval_id])
            fingerprint = scores.fingerprint
            before = previous[cid].get(fingerprint, {})
            for task_name, new in sorted(scores.success_rates.items()):
                old = before.get(task_name)
                changes.append(
                    {
                        "checkpoint_id": cid,
                        "task": task_name,
                        "previous": old,
                        "new": new,
                        "changed": old is not None and abs(old - new) > 1e-9,
                        "evaluation_id": eval_id,
                        "fingerprint": fingerprint,
                    }
                )
        publish_markdown("reevaluation-summary", summary_markdown(changes), "scores before and after")
    return changes


def summary_markdown(changes: list[dict[str, Any]]) -> str:
    lines = ["| checkpoint | task | previous | new | changed |", "|---|---|---|---|---|"]
    for c in changes:
        prev = "-" if c["previous"] is None else f"{c['previous']:.3f}"
        lines.append(
            f"| {c['checkpoint_id'][:12]} | {c['task']} | {prev} | {c['new']:.3f} | {c['changed']} |"
        )
    return "\n".join(lines) + "\n"
