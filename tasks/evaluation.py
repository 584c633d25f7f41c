"""Step: evaluate a checkpoint on Meta-World under one protocol and record every episode."""

from __future__ import annotations

from typing import Any

from prefect.artifacts import create_table_artifact

from artifacts.scores import read_scores
from capvector_core.evaluation import EvalConfig, EvalResult, evaluate
from tasks.caching import cached_step
from tasks.prefect_task import pipeline_task
from tasks.progress import progress_printer
from tasks.trained_policy import load_trained_policy
from tasks.workspace import Workspace, provenance


def evaluation_doc(checkpoint_id: str, result: EvalResult, versions: dict[str, Any]) -> dict[str, Any]:
    """The store's evaluation document (artifacts.records.EvaluationDoc) from a core EvalResult.

    Its content, hence its id: what the checkpoint, the protocol and the library versions determine,
    nothing else. When it ran, how long it took, where videos were written are provenance and go into
    the record's config (its sidecar), never here, so one evaluation run twice has one id. Its scores
    are not in the sidecar either: the catalogue derives them from these episodes
    (artifacts.scores)."""
    return {
        "checkpoint_id": checkpoint_id,
        "fingerprint": result.fingerprint,
        "library_versions": {**versions, **result.versions},
        "episodes": [
            {
                "task": e.task,
                "seed": e.seed,
                "success": e.success,
                "steps": e.steps,
                "return": e.episode_return,
            }
            for e in result.episodes
        ],
    }


def evaluate_checkpoint(
    workspace: Workspace, step: str, checkpoint_id: str, config: dict[str, Any], cache_key: str | None = None
) -> str:
    """Run the rollouts now (no cache) and register the evaluation; returns its artifact id."""
    eval_config = EvalConfig.model_validate(config)
    policy, form = load_trained_policy(workspace, checkpoint_id, device="auto")
    result = evaluate(policy.predict_action_chunk, eval_config, progress=progress_printer(step, "episodes"))
    meta = provenance()
    record = workspace.api.register_evaluation(
        evaluation_doc(workspace.api.get(checkpoint_id).id, result, meta["library_versions"]),
        name=step,
        config={
            "eval": eval_config.model_dump(mode="json"),
            "policy_form": form.model_dump(mode="json"),
            "protocol": result.protocol,
            "wall_time_s": result.wall_time_s,
            "env_steps": result.env_steps,
            "cache_key": cache_key,
        },
        **meta,
    )
    (scores,) = read_scores(workspace.api, evaluations=[record.id])  # as every other reader sees them
    create_table_artifact(
        table=[{"task": t, "success_rate": r} for t, r in sorted(scores.success_rates.items())],
        key=f"evaluation-{record.id[:12]}",
        description=f"{step}: checkpoint {checkpoint_id[:12]}, protocol {result.fingerprint[:12]}",
    )
    return record.id


def run_evaluate(workspace: Workspace, step: str, inputs: dict[str, str], config: dict[str, Any]) -> str:
    if "checkpoint" not in inputs:
        raise ValueError(f"step {step!r}: evaluate needs a 'checkpoint' input")
    EvalConfig.model_validate(config)  # fail before any cache lookup on a bad protocol
    return cached_step(
        workspace,
        "evaluate",
        inputs,
        config,
        lambda key: evaluate_checkpoint(workspace, step, inputs["checkpoint"], config, cache_key=key),
    )


@pipeline_task("evaluate")
def evaluate_task(home: str, step: str, inputs: dict[str, str], config: dict[str, Any]) -> str:
    return run_evaluate(Workspace(home), step, inputs, config)


@pipeline_task("reevaluate", content_cached=False)
def reevaluate_task(home: str, step: str, inputs: dict[str, str], config: dict[str, Any]) -> str:
    """Always re-runs: the cache key has a fresh nonce unless this exact run already landed."""
    return evaluate_checkpoint(Workspace(home), step, inputs["checkpoint"], config)
