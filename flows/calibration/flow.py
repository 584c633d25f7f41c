"""The `calibrate` flow: runs a calibration's plan (capvector.flows.calibration.plan) on the task runner,
recorded as a run.

Kept apart from the plan so that a calibration the content cache answers whole never imports Prefect.
"""

from __future__ import annotations

from typing import Any

from prefect import flow

from capvector.flows.calibration.config import CalibrateConfig
from capvector.flows.calibration.plan import calibration_steps, plan_calibration
from capvector.flows.runtime.run_records import publish_markdown, recorded_run, run_name
from capvector.flows.runtime.step_pool import step_runner
from capvector.flows.runtime.step_submission import StepRunner
from capvector.tasks.runtime.workspace import workspace_for


@flow(
    name="calibrate", flow_run_name=run_name, log_prints=True, task_runner=step_runner(), persist_result=False
)
def calibrate_flow(config: dict[str, Any], home: str) -> dict[str, Any]:
    """Run (or resume from cache) a calibration; returns plan_calibration's result."""
    cfg = CalibrateConfig.model_validate(config)
    workspace = workspace_for(home)
    steps = StepRunner(home, calibration_steps(cfg), f"calibrate {cfg.name}")
    with recorded_run(workspace, "calibrate", {"config": config, "home": home}):
        result = plan_calibration(cfg, steps)
        publish_markdown(f"{cfg.name}-calibration", result["markdown"], f"capvector calibrate {cfg.name}")
    return result
