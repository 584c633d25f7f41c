"""A downstream arm's run (`submit_arm`), without Prefect: every study's compared and tuning runs,
including a sweep's α × λ cells (capvector.flows.study.plan).

    demos(D_pt, D_ext, D_down) -> θ_pt -> {θ_ft, θ_ao} on D_ext -> γ = θ_ao − θ_ft -> θ_meta = θ_pt + α·γ

The recipe run once (`capvector run`) and its α × λ sweep (`capvector sweep`) are studies
(capvector.flows.study.recipe), planned by capvector.flows.study.plan.
"""

from __future__ import annotations

from typing import Any

from capvector.flows.recipe.config import ARMS
from capvector.flows.runtime.step_submission import StepRunner
from capvector.tasks.steps.training import TrainStepConfig, train_task


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
    tuning cell's α) in place of the stage's; `selection`, the choice of a value the run uses."""
    spec = ARMS[arm]
    init = meta if spec.init == "meta" and meta is not None else stage[spec.init]
    inputs = {"data": stage["data"]["downstream"], "init": init}
    if spec.orthogonal:
        inputs["vector"] = stage["null_vector" if spec.init == "null_meta" else "vector"]
    if selection is not None:
        inputs["selection"] = selection
    config = step_config.model_dump(mode="json")
    return steps.submit(train_task, label or f"downstream {arm} seed {seed}", inputs, config)
