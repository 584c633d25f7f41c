"""How a training step fine-tunes: full weights, LoRA, LoRA-SP or AdaLoRA, as entries of one registry.

Each entry knows what its form does at every point of a training step, so `capvector.tasks.steps.training`
asks the entry instead of branching on its name: its config section (and what it refuses in it), how it is
applied to the model, the extra losses it trains with, what runs after each optimizer step, which
orthogonal-loss mode it takes, and how it ends (the adapter saved as its own artifact, then merged so the
checkpoint holds dense weights). A new form is one class here (peft's
`register_peft_method` pattern).
"""

from __future__ import annotations

import copy
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar

import torch
from pydantic import BaseModel
from torch import nn

from capvector.core.adapters import adalora, lora, lora_sp
from capvector.core.policies.base import save_policy

SNAPSHOT_ADAPTER = "{stem}.{file}"
"""A snapshot's adapter files beside its weights (`snapshots/step_00000050.adapter_config.json`): flat
files, so the run's checkpoint mirror (capvector.tasks.runtime.scratch) copies them with the weights."""


class Adapter:
    """Full fine-tuning: every parameter trains, nothing to save besides the weights."""

    name: ClassVar[str] = "full"
    section: ClassVar[str | None] = None
    """The `TrainStepConfig` field holding this form's settings (None: it needs none)."""
    evaluated_as_adapter: ClassVar[bool] = False
    """Whether its checkpoints are evaluated as `init` + the adapter (their dense merge is approximate)."""

    def settings(self, step: Any) -> BaseModel | None:
        return getattr(step, self.section) if self.section else None

    def check(self, step: Any) -> None:
        """Refuse settings of the step this form cannot run (when the step's config is validated)."""

    def apply(self, model: nn.Module, step: Any) -> None:
        """Turn the model into what trains (adapter layers, frozen base) before the optimizer sees it."""

    def extra_losses(self) -> dict[str, Callable[..., Any]]:
        return {}

    def after_optimizer_step(self, model: nn.Module) -> Callable[[int], None] | None:
        """The trainer's `after_optimizer_step` hook for the applied `model` (None: nothing to do)."""
        return None

    def orthogonal_mode(self, lora_mode: str) -> str:
        """The regularizer's mode: the dense Δ' for full weights, the adapter's form otherwise."""
        return "dense"

    def finish(
        self, model: nn.Module, folder: Path, calibration: Callable[[], list[Any]], summary: dict[str, Any]
    ) -> Path | None:
        """After training: the adapter folder to register (None: none), with the model merged dense."""
        return None

    def snapshot(self, model: nn.Module, path: Path, calibration: Callable[[], list[Any]]) -> None:
        """The policy kept at a snapshot step, written to `path`: the weights themselves for full
        fine-tuning; for an adapter, a copy of the model finished as the run will be (merged dense), the
        training model untouched, and beside it the adapter's files where evaluation runs the adapter."""
        if self.section is None:
            save_policy(model, path)
            return
        kept = _copy(model)
        folder = path.parent / f".{path.stem}.adapter"
        shutil.rmtree(folder, ignore_errors=True)
        self.finish(kept, folder, calibration, {})
        if self.evaluated_as_adapter:  # the adapter's files first: the weights file marks the snapshot whole
            for f in sorted(folder.iterdir()):
                os.replace(f, path.parent / SNAPSHOT_ADAPTER.format(stem=path.stem, file=f.name))
        shutil.rmtree(folder, ignore_errors=True)
        save_policy(kept, path)


def _copy(model: nn.Module) -> nn.Module:
    """A deep copy of a training model: tensors a layer kept from its last forward (LoRA-SP's losses, still
    in the graph, which deepcopy refuses) are copied detached."""
    memo: dict[int, Any] = {}
    for module in model.modules():
        for value in vars(module).values():
            for t in value.values() if isinstance(value, dict) else (value,):
                if isinstance(t, torch.Tensor) and not t.is_leaf:
                    memo[id(t)] = t.detach()
    return copy.deepcopy(model, memo)


def snapshot_adapter_files(path: Path) -> list[Path]:
    """The adapter files written beside snapshot `path` (none for full fine-tuning, LoRA, AdaLoRA)."""
    return sorted(p for p in path.parent.glob(f"{path.stem}.*") if p != path)


class LoraAdapter(Adapter):
    """LoRA through peft: saved in peft's layout, then merged into the dense weights."""

    name = "lora"
    section = "lora"

    def apply(self, model: nn.Module, step: Any) -> None:
        lora.apply_lora(model, step.lora)

    def orthogonal_mode(self, lora_mode: str) -> str:
        return lora_mode

    def finish(self, model, folder, calibration, summary) -> Path | None:
        saved = lora.save_adapter(model, folder)
        lora.merge_lora(model)
        return saved


class LoraSPAdapter(LoraAdapter):
    """Rank-adaptive LoRA-SP: trains with its own loss; its dense merge is calibrated on training
    batches (an approximation: evaluation runs the adapter itself, capvector.tasks.trained_policy)."""

    name = "lora_sp"
    section = "lora_sp"
    evaluated_as_adapter = True

    def apply(self, model: nn.Module, step: Any) -> None:
        lora_sp.apply_lora_sp(model, step.lora_sp)

    def extra_losses(self) -> dict[str, Callable[..., Any]]:
        return {"lora_sp": lora_sp.lora_sp_loss}

    def finish(self, model, folder, calibration, summary) -> Path | None:
        lora_sp.calibrate(model, calibration(), forward=_policy_loss)
        summary["active_ranks"] = lora_sp.active_ranks(model, since_reset=True)
        saved = lora_sp.save_adapter(model, folder)
        lora.merge_lora(model)
        return saved


class AdaLoraAdapter(LoraAdapter):
    """peft's AdaLoRA: ranks reallocated after each optimizer step (its allocator's state resumes with the
    run), its orthogonal regularizer an extra loss; saved in peft's layout, merged exactly."""

    name = "adalora"
    section = "adalora"

    def check(self, step: Any) -> None:
        step.adalora.schedule(step.train.steps)

    def apply(self, model: nn.Module, step: Any) -> None:
        adalora.apply_adalora(model, step.adalora, step.train.steps)

    def extra_losses(self) -> dict[str, Callable[..., Any]]:
        return {"adalora_orth": adalora.orthogonality_loss}

    def after_optimizer_step(self, model: nn.Module) -> Callable[[int], None] | None:
        return adalora.schedule(model)

    def finish(self, model, folder, calibration, summary) -> Path | None:
        summary["active_ranks"] = adalora.ranks(model)
        saved = adalora.save_adapter(model, folder)
        adalora.merge_adalora(model)
        return saved


def _policy_loss(model: Any, batch: dict[str, Any]) -> None:
    """Calibration runs the policy's own loss: every policy type has one (not all have `forward`)."""
    model.compute_loss(batch)


ADAPTERS: dict[str, Adapter] = {
    a.name: a for a in (Adapter(), LoraAdapter(), LoraSPAdapter(), AdaLoraAdapter())
}
