"""The policy a checkpoint stands for, as it was trained.

A checkpoint holds dense weights, so vectors can be taken from any of them. For full fine-tuning and
LoRA those weights are the trained policy exactly. A LoRA-SP adapter whose router depends on the
input is not: its dense merge replaces each token's score vector with the mean over calibration
batches, and on the `hard` setting that approximation lost about half the success of the adapter
itself (docs/studies/results_hard_adapters.md). So an evaluation of such a checkpoint runs its `init`
weights with the adapter applied, and says so in its record.
"""

from __future__ import annotations

from pydantic import BaseModel

from capvector.core.adapters import lora_sp
from capvector.core.adapters.lora import read_adapter
from capvector.core.policies.base import Policy, load_policy, read_policy_config
from capvector.tasks.runtime.workspace import Workspace


class PolicyForm(BaseModel):
    """Which weights an evaluation ran: the checkpoint's own, or `init` + a LoRA-SP adapter."""

    form: str  # "dense" | "lora_sp_adapter"
    adapter_id: str | None = None
    init_id: str | None = None


def policy_form(workspace: Workspace, checkpoint_id: str) -> PolicyForm:
    """`lora_sp_adapter` when the checkpoint came from a LoRA-SP run (its dense merge is approximate)."""
    parents = {p.role: p.id for p in workspace.api.get(checkpoint_id).parents}
    adapter_id = parents.get("adapter")
    if adapter_id is None:
        return PolicyForm(form="dense")
    doc, _ = read_adapter(workspace.path(adapter_id))
    if doc.get("peft_type") != "LORA_SP":
        return PolicyForm(form="dense")
    init_id = parents.get("init")
    if init_id is None:
        raise ValueError(
            f"checkpoint {checkpoint_id[:12]} has a LoRA-SP adapter {adapter_id[:12]} but no `init` parent "
            "to apply it to"
        )
    return PolicyForm(form="lora_sp_adapter", adapter_id=adapter_id, init_id=init_id)


def load_trained_policy(
    workspace: Workspace, checkpoint_id: str, device: str = "auto"
) -> tuple[Policy, PolicyForm]:
    """The policy to evaluate for `checkpoint_id`, and which form it is in."""
    form = policy_form(workspace, checkpoint_id)
    if form.form == "dense":
        return load_policy(workspace.path(checkpoint_id), device=device), form
    policy = load_policy(workspace.path(form.init_id), device=device)
    lora_sp.load_adapter(policy, workspace.path(form.adapter_id))
    return policy, form


def resolve_checkpoints(workspace: Workspace, refs: list[str]) -> list[str]:
    """Checkpoint ids for `capvector evaluate`'s arguments: an artifact id (or unique prefix) as it is, a
    file or folder path imported into the store first. Each must name a registered policy type (in its
    weights' metadata or, for a folder, its config.json); one that does not is refused in one line, with
    how to register one, before any flow starts."""
    from pathlib import Path

    from capvector.tasks.vector_commands import import_path

    ids = []
    for ref in refs:
        record = import_path(workspace, ref) if Path(ref).exists() else workspace.api.get(ref)
        read_policy_config(workspace.path(record.id))
        ids.append(record.id)
    return ids
