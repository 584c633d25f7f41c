"""Step: evaluate a checkpoint on Meta-World under one protocol and record every episode."""

from __future__ import annotations

from typing import Any

from capvector.artifacts.scores import read_scores
from capvector.core.evaluation.rollouts import EvalConfig, EvalResult, evaluate
from capvector.tasks.runtime.prefect_task import artifact_key
from capvector.tasks.runtime.progress import progress_printer
from capvector.tasks.runtime.step_kinds import StepCall, StepKind, step_task
from capvector.tasks.runtime.workspace import Workspace, provenance
from capvector.tasks.trained_policy import load_trained_policy

VIDEO_KIND = "video"
"""A rollout video, registered with its evaluation as parent (role `of`): an mp4, or a GIF in homes
written before videos were mp4s (read alike: nothing here opens the file)."""


def evaluation_doc(checkpoint_id: str, result: EvalResult, versions: dict[str, Any]) -> dict[str, Any]:
    """The store's evaluation document (capvector.artifacts.records.EvaluationDoc) from a core EvalResult.

    Its content, hence its id: what the checkpoint, the protocol and the library versions determine,
    nothing else. When it ran, how long it took, where videos were written are provenance and go into
    the record's config (its sidecar), never here, so one evaluation run twice has one id. Its scores
    are not in the sidecar either: the catalogue derives them from these episodes
    (capvector.artifacts.scores)."""
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
    workspace: Workspace,
    step: str,
    checkpoint_id: str,
    config: dict[str, Any] | EvalConfig,
    cache_key: str | None = None,
) -> str:
    """Run the rollouts now (no cache) and register the evaluation; returns its artifact id."""
    eval_config = EvalConfig.model_validate(config)
    policy, form = load_trained_policy(workspace, checkpoint_id, device="auto")
    with workspace.scratch() as video_dir:
        result = evaluate(
            policy.predict_action_chunk, eval_config, progress_printer(step, "episodes"), video_dir=video_dir
        )
        record = _register(workspace, step, checkpoint_id, eval_config, result, form, cache_key)
        videos = {
            name: workspace.api.register_file(
                path, VIDEO_KIND, f"{step}: {name}", parents=[(record.id, "of")]
            )
            for name, path in sorted(result.videos.items())
        }
    from prefect.artifacts import create_markdown_artifact, create_table_artifact  # only when it ran

    (scores,) = read_scores(workspace.api, evaluations=[record.id])  # as every other reader sees them
    create_table_artifact(  # keyed by the step, so the UI shows an arm's (draw's, seed's) history
        table=[{"task": t, "success_rate": r} for t, r in sorted(scores.success_rates.items())],
        key=artifact_key(f"evaluation {step}"),
        description=f"{step}: evaluation {record.id[:12]} of checkpoint {checkpoint_id[:12]}, protocol "
        f"{result.fingerprint[:12]}",
    )
    if videos:
        links = "\n".join(
            f"- {name}: `{v.id[:12]}` ({workspace.api.path(v.id)})" for name, v in videos.items()
        )
        create_markdown_artifact(
            markdown=f"Rollout videos of {step}:\n\n{links}\n", key=artifact_key(f"videos {step}")
        )
    return record.id


def video_ids_of(workspace: Workspace, evaluation_ids: list[str]) -> dict[str, list[tuple[str, str]]]:
    """Evaluation id -> [(video name, video artifact id)] of the rollout videos registered with it, by
    name (every run that recorded some: mp4s, and GIFs recorded before)."""
    if not evaluation_ids:
        return {}
    marks = ", ".join("?" for _ in evaluation_ids)
    _, rows = workspace.api.query_rows(
        f"SELECT e.parent, a.id, a.name FROM edges e JOIN artifacts a ON a.id = e.child "
        f"WHERE a.kind = '{VIDEO_KIND}' AND e.parent IN ({marks}) ORDER BY a.name, a.created_at",
        list(evaluation_ids),
    )
    found: dict[str, list[tuple[str, str]]] = {}
    for parent, video, name in rows:
        found.setdefault(parent, []).append((name, video))
    return found


def videos_of(workspace: Workspace, evaluation_ids: list[str]) -> dict[str, list[tuple[str, str]]]:
    """Evaluation id -> [(video name, path)] of the rollout videos registered with it."""
    return {
        parent: [(name, str(workspace.api.path(video))) for name, video in videos]
        for parent, videos in video_ids_of(workspace, evaluation_ids).items()
    }


def _register(
    workspace: Workspace,
    step: str,
    checkpoint_id: str,
    eval_config: EvalConfig,
    result: EvalResult,
    form: Any,
    cache_key: str | None,
) -> Any:
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
    return record


def _evaluate(call: StepCall) -> str:
    return evaluate_checkpoint(call.workspace, call.step, call.inputs["checkpoint"], call.config, call.key)


EVALUATE = StepKind("evaluate", EvalConfig, ("checkpoint",), _evaluate, key_on_model=True)
REEVALUATE = StepKind("reevaluate", EvalConfig, ("checkpoint",), _evaluate, content_cached=False)
"""Always re-runs: the cache key has a fresh nonce unless this exact run already landed."""
evaluate_task = step_task(EVALUATE)
reevaluate_task = step_task(REEVALUATE)
