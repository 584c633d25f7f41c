"""Step: a checkpoint's action loss on held-out demonstrations (the extraction runs' convergence check).

The measure is `capvector.core.training.held_out_loss.held_out_action_loss`, on the policy as it was trained
and is evaluated (capvector.tasks.trained_policy): for a LoRA-SP checkpoint, its init with the adapter
applied. Such a checkpoint's dense merge is an approximation, so its loss is recorded too
(`merged_action_loss`): merged − as trained is the merge's error. Recorded as a `measurement` artifact whose
parents are the checkpoint and the data.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from capvector.core.simulation.demos import DemoDataset
from capvector.core.training.held_out_loss import held_out_action_loss
from capvector.tasks.runtime.step_kinds import StepCall, StepKind, step_task
from capvector.tasks.runtime.workspace import Workspace, provenance
from capvector.tasks.trained_policy import load_trained_policy

MEASUREMENT_KIND = "measurement"


class HeldOutLossConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    batch_size: int = Field(256, gt=0)
    seed: int = 0


def _measure(call: StepCall) -> str:
    workspace, inputs, cfg = call.workspace, call.inputs, call.config
    dataset = DemoDataset.load(workspace.path(inputs["data"]))
    policy, form = load_trained_policy(workspace, inputs["checkpoint"], device="cpu")
    doc = {
        "checkpoint_id": inputs["checkpoint"],
        "data_id": inputs["data"],
        "action_loss": held_out_action_loss(policy, dataset, cfg.batch_size, cfg.seed),
        "form": form.form,
        "samples": len(dataset),
    }
    if form.form != "dense":
        dense = workspace.path(inputs["checkpoint"])
        doc["merged_action_loss"] = held_out_action_loss(dense, dataset, cfg.batch_size, cfg.seed)
    record = workspace.api.register_json(
        doc,
        kind=MEASUREMENT_KIND,
        name=call.step,
        config={"measure": "held-out action loss", **cfg.model_dump(), "cache_key": call.key},
        parents=[(inputs["checkpoint"], "measured"), (inputs["data"], "data")],
        **provenance(),
    )
    return record.id


def measured_loss(workspace: Workspace, measurement_id: str) -> float:
    return float(workspace.api.store.open_json(measurement_id)["action_loss"])


def merge_error(workspace: Workspace, measurement_id: str) -> float | None:
    """Merged − as-trained held-out loss of a checkpoint whose dense merge approximates it; else None."""
    doc = workspace.api.store.open_json(measurement_id)
    merged = doc.get("merged_action_loss")
    return None if merged is None else float(merged) - float(doc["action_loss"])


HELD_OUT_LOSS = StepKind("held_out_loss", HeldOutLossConfig, ("checkpoint", "data"), _measure)
held_out_loss_task = step_task(HELD_OUT_LOSS)
