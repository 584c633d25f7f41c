"""The `study` flow: runs a study's plan (capvector.flows.study.plan) on the task runner, recorded as a run.

Kept apart from the plan so that a study the content cache answers whole never imports Prefect.
"""

from __future__ import annotations

from typing import Any

from prefect import flow

from capvector.flows.runtime.run_records import publish_markdown, recorded_run, run_name
from capvector.flows.runtime.step_pool import step_runner
from capvector.flows.runtime.step_submission import StepRunner
from capvector.flows.study.config import StudyConfig
from capvector.flows.study.plan import plan_study, study_steps
from capvector.tasks.runtime.workspace import workspace_for


@flow(name="study", flow_run_name=run_name, log_prints=True, task_runner=step_runner(), persist_result=False)
def study_flow(config: dict[str, Any], home: str) -> dict[str, Any]:
    """Run (or resume from cache) a study (or a sweep, capvector.flows.study.recipe.sweep_study); returns
    the report's id (a sweep's selection's) and the selections' ids."""
    cfg = StudyConfig.model_validate(config)
    workspace = workspace_for(home)
    before_gate, after_gate = study_steps(cfg)
    steps = StepRunner(home, before_gate, f"study {cfg.name}", after_gate=after_gate)
    with recorded_run(workspace, "study", {"config": config, "home": home}):
        result = plan_study(cfg, steps)
        what = "study" if cfg.study.sweep_arm is None else "sweep"  # a sweep's Markdown: its α × λ table
        publish_markdown(f"{cfg.name}-{what}", result["markdown"], f"capvector {what} {cfg.name}")
    return result
