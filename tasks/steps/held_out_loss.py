"""Step: a checkpoint's action loss on held-out demonstrations (the extraction runs' convergence check).

The measure is `capvector.core.training.held_out_loss.held_out_action_loss`. Recorded as a `measurement`
artifact whose
parents are the checkpoint and the data.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from capvector.core.simulation.demos import DemoDataset
from capvector.core.training.held_out_loss import held_out_action_loss
from capvector.tasks.runtime.caching import cached_step
from capvector.tasks.runtime.prefect_task import pipeline_task
from capvector.tasks.runtime.workspace import Workspace, provenance, workspace_for

MEASUREMENT_KIND = "measurement"


class HeldOutLossConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    batch_size: int = Field(256, gt=0)
    seed: int = 0


def run_held_out_loss(workspace: Workspace, step: str, inputs: dict[str, str], config: dict[str, Any]) -> str:
    cfg = HeldOutLossConfig.model_validate(config)
    for role in ("checkpoint", "data"):
        if role not in inputs:
            raise ValueError(f"step {step!r}: a held-out loss needs a {role!r} input")

    def produce(key: str) -> str:
        dataset = DemoDataset.load(workspace.path(inputs["data"]))
        loss = held_out_action_loss(workspace.path(inputs["checkpoint"]), dataset, cfg.batch_size, cfg.seed)
        doc = {
            "checkpoint_id": inputs["checkpoint"],
            "data_id": inputs["data"],
            "action_loss": loss,
            "samples": len(dataset),
        }
        record = workspace.api.register_json(
            doc,
            kind=MEASUREMENT_KIND,
            name=step,
            config={"measure": "held-out action loss", **cfg.model_dump(), "cache_key": key},
            parents=[(inputs["checkpoint"], "measured"), (inputs["data"], "data")],
            **provenance(),
        )
        return record.id

    return cached_step(workspace, "held_out_loss", inputs, config, produce)


def measured_loss(workspace: Workspace, measurement_id: str) -> float:
    return float(workspace.api.store.open_json(measurement_id)["action_loss"])


@pipeline_task("held_out_loss")
def held_out_loss_task(home: str, step: str, inputs: dict[str, str], config: dict[str, Any]) -> str:
    return run_held_out_loss(workspace_for(home), step, inputs, config)
