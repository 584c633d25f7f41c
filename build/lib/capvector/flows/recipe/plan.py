"""The recipe's steps as a plan, without Prefect: what the `pipeline` flow (capvector.flows.recipe.flow)
submits.

    demos(D_pt, D_ext, D_down) -> θ_pt -> {θ_ft, θ_ao} on D_ext -> γ = θ_ao − θ_ft -> θ_meta = θ_pt + α·γ
    -> downstream arms × seeds on D_down -> evaluation under one protocol -> comparison report

`run_pipeline` submits to whatever runner it is given: the flow's StepRunner, the CLI's CacheProbe
(a run the content cache answers whole never imports Prefect) or a PlanRecorder (the step total and
`--dry-run`). The study and sweep build on `submit_vector_stage` and `submit_arm`.
"""

from __future__ import annotations

from typing import Any

from capvector.flows.recipe.config import ARMS, PipelineConfig
from capvector.flows.runtime.step_submission import PlannedStep, StepRunner, record_plan, resolve
from capvector.tasks.steps.data import collect_demos_task
from capvector.tasks.steps.evaluation import evaluate_task
from capvector.tasks.steps.reporting import report_task
from capvector.tasks.steps.training import TrainStepConfig, train_task
from capvector.tasks.steps.vectors import extract_task, merge_task


def _dump(model: Any) -> dict[str, Any]:
    return model.model_dump(mode="json")


def submit_vector_stage(steps: StepRunner, config: PipelineConfig) -> dict[str, Any]:
    """Ids or futures of demos, θ_pt, θ_ft, θ_ao, γ and θ_meta."""
    data = {
        split: steps.submit(collect_demos_task, f"demos {split}", {}, _dump(config.demo_config(split)))
        for split in ("pretrain", "extraction", "downstream")
    }
    pretrained = steps.submit(
        train_task, "pretrain θ_pt", {"data": data["pretrain"]}, _dump(config.pretrain_step())
    )
    extraction_inputs = {"data": data["extraction"], "init": pretrained}
    standard = steps.submit(
        train_task, "standard SFT θ_ft", extraction_inputs, _dump(config.extraction_step(False))
    )
    auxiliary = steps.submit(
        train_task, "auxiliary SFT θ_ao", extraction_inputs, _dump(config.extraction_step(True))
    )
    vector = steps.submit(
        extract_task,
        "capability vector γ",
        {"minuend": auxiliary, "subtrahend": standard, "base": pretrained},
        _dump(config.vector),
    )
    meta = steps.submit(
        merge_task,
        f"merge θ_meta (α={config.alpha})",
        {"base": pretrained, "vector": vector},
        _dump(config.merge_config()),
    )
    return {
        "data": data,
        "pretrained": pretrained,
        "standard": standard,
        "auxiliary": auxiliary,
        "vector": vector,
        "meta": meta,
    }


def submit_arm(
    steps: StepRunner,
    stage: dict[str, Any],
    arm: str,
    seed: int,
    step_config: TrainStepConfig,
    *,
    label: str | None = None,
    meta: Any = None,
    selection: Any = None,
) -> Any:
    """Id or future of one downstream checkpoint (arm × seed), trained as `step_config` says. `stage`
    holds what the arm's `init` names (`pretrained`, `meta`, ...); `meta` is a θ_meta of its own (a
    sweep's α) in place of the stage's; `selection`, the choice of a value the run uses."""
    spec = ARMS[arm]
    init = meta if spec.init == "meta" and meta is not None else stage[spec.init]
    inputs = {"data": stage["data"]["downstream"], "init": init}
    if spec.orthogonal:
        inputs["vector"] = stage["null_vector" if spec.init == "null_meta" else "vector"]
    if selection is not None:
        inputs["selection"] = selection
    return steps.submit(train_task, label or f"downstream {arm} seed {seed}", inputs, _dump(step_config))


def _submit_ood_report(steps: StepRunner, config: PipelineConfig, checkpoints: dict[str, Any]) -> str | None:
    """The same final checkpoints, tested through `evaluation.ood_camera`, in a report of their own."""
    camera = config.evaluation.ood_camera
    if camera is None:
        return None
    eval_config = _dump(config.eval_config(camera=camera))
    evaluations = {
        label: steps.submit(evaluate_task, f"evaluate {label} ({camera})", {"checkpoint": ckpt}, eval_config)
        for label, ckpt in checkpoints.items()
    }
    name = f"{config.name} ood camera {camera}"
    return resolve(steps.submit(report_task, f"report {name}", evaluations, {"name": name}))


def pipeline_plan(config: PipelineConfig) -> list[PlannedStep]:
    """Every step a pipeline run submits, in order: the flow's own submissions, recorded."""
    return record_plan(lambda steps: run_pipeline(steps, config))


def pipeline_steps(config: PipelineConfig) -> int:
    """How many steps a pipeline run has (progress shows `k/N`): `len(plan)`."""
    return len(pipeline_plan(config))


def run_pipeline(steps: StepRunner, cfg: PipelineConfig) -> dict[str, Any]:
    """Submit the recipe's steps to `steps` (a flow's runner, or a CacheProbe); the products' ids."""
    stage = submit_vector_stage(steps, cfg)
    eval_config = _dump(cfg.eval_config())
    checkpoints = {
        f"{arm}/seed{seed}": submit_arm(steps, stage, arm, seed, cfg.downstream_step(arm, seed))
        for arm in cfg.arms
        for seed in cfg.seeds
    }
    evaluations = {
        label: steps.submit(evaluate_task, f"evaluate {label}", {"checkpoint": ckpt}, eval_config)
        for label, ckpt in checkpoints.items()
    }
    # Results in the order the steps depend on each other: a failed step raises its own error here
    # (naming the step), not a later step's UpstreamTaskError naming a task-run id.
    ids = {
        "datasets": {k: resolve(f) for k, f in stage["data"].items()},
        **{k: resolve(stage[k]) for k in ("pretrained", "standard", "auxiliary", "vector", "meta")},
        "checkpoints": {k: resolve(f) for k, f in checkpoints.items()},
        "evaluations": {k: resolve(f) for k, f in evaluations.items()},
    }
    report_step = steps.submit(report_task, f"report {cfg.name}", ids["evaluations"], {"name": cfg.name})
    ids["report"] = resolve(report_step)
    ood_report = _submit_ood_report(steps, cfg, ids["checkpoints"])
    if ood_report is not None:
        ids["ood_report"] = ood_report
    return ids
