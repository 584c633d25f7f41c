"""The recipe's shared submissions, without Prefect: a downstream arm's run (`submit_arm`, every study's
compared and tuning runs) and the vector stage of one γ (`submit_vector_stage`, the `sweep` flow's).

    demos(D_pt, D_ext, D_down) -> θ_pt -> {θ_ft, θ_ao} on D_ext -> γ = θ_ao − θ_ft -> θ_meta = θ_pt + α·γ

The recipe run once (`capvector run`) is a study (capvector.flows.study.recipe), planned by
capvector.flows.study.plan.
"""

from __future__ import annotations

from typing import Any

from capvector.flows.recipe.config import ARMS, PipelineConfig
from capvector.flows.runtime.step_submission import StepRunner
from capvector.tasks.steps.data import collect_demos_task
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
