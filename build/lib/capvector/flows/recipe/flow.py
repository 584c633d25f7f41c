"""The `pipeline` flow: the whole CapVector recipe with its baselines (capvector.flows.recipe.plan), cached
step by step.

Independent branches are submitted together and run concurrently on the task runner
(capvector.flows.runtime.step_submission:
a step the content cache answers runs in the flow's process, the others in the pool): a pool of
processes, because steps seed torch's process-global RNG and must not share it, and because two
training steps in two processes use both cores without contending for the GIL. Each worker is bound
to the process that started it (capvector.tasks.runtime.prefect_task.bind_worker_to_parent): a killed CLI
takes its workers, and their embedded API servers, along.
"""

from __future__ import annotations

from typing import Any

from prefect import flow

from capvector.flows.recipe.config import PipelineConfig
from capvector.flows.recipe.plan import pipeline_steps, run_pipeline
from capvector.flows.runtime.run_records import publish_markdown, recorded_run, run_name
from capvector.flows.runtime.step_pool import StepPool
from capvector.flows.runtime.step_submission import StepRunner
from capvector.tasks.runtime.prefect_task import bind_worker_to_parent
from capvector.tasks.runtime.workspace import workspace_for
from capvector.tasks.steps.reporting import load_report


def step_runner(workers: int = 2) -> StepPool:
    return StepPool(max_workers=workers, initializer=bind_worker_to_parent)


@flow(
    name="pipeline", flow_run_name=run_name, log_prints=True, task_runner=step_runner(), persist_result=False
)
def pipeline(config: dict[str, Any], home: str) -> dict[str, Any]:
    """Run (or resume from cache) the recipe; returns the artifact ids of every product."""
    cfg = PipelineConfig.model_validate(config)
    workspace = workspace_for(home)
    steps = StepRunner(home, pipeline_steps(cfg), f"pipeline {cfg.name}")
    with recorded_run(workspace, "pipeline", {"config": config, "home": home}):
        ids = run_pipeline(steps, cfg)
        summary = load_report(workspace, ids["report"]).markdown
        publish_markdown(f"{cfg.name}-summary", summary, f"capvector pipeline {cfg.name}")
    return ids
