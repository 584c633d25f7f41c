"""AdaLoRA (Zhang et al., ICLR 2023) through peft: LoRA whose rank per layer is allocated during training.

Per adapted linear layer, peft's `SVDLinear`: ΔW = B·diag(E)·A·alpha/(init_r + 1e-5), A (init_r × in) and
B (out × init_r) the singular vectors, E (init_r × 1) the singular values (starting at zero, so an adapted
model starts equal to its base). The rank allocator (peft's `RankAllocator`) scores every triplet
(A row, E entry, B column) by a smoothed sensitivity |θ·∇θ| (EMAs with beta1, beta2) and, after each
optimizer step, zeroes the E entries of the least important triplets over all layers together, so the total
budget falls from init_r per layer to target_r per layer on average, on a cubic schedule: full budget for
the first tinit steps, pruning up to step total − tfinal, where the allocation is fixed for the last tfinal
steps. Layers end with different ranks (some may end at 0).

This module wires peft's pieces into this project's loop, which peft expects the caller to do:
- `apply_adalora(model, config, total_steps)` injects peft's layers through peft's `AdaLoraModel` (as
  `peft.inject_adapter_in_model` does) and keeps that tuner in a `RankSchedule` on the model
  (`model.adalora_schedule`): the trainer's `after_optimizer_step` hook calls it, which runs peft's
  `update_and_allocate(step)` after each optimizer step (gradients still in place). Its state (the
  allocator's EMAs and the rank pattern) is saved in every checkpoint, so a resumed run is exact.
- `orthogonality_loss(model)`: peft adds AdaLoRA's orthogonal regularizer only in `AdaLoraModel.forward`,
  and only when the model's output has a `.loss`; our policies compute their loss themselves, so it is an
  extra loss here, with peft's arithmetic: orth_reg_weight × the mean over all A and B matrices of
  ‖A·Aᵀ − I‖_F and ‖Bᵀ·B − I‖_F (Frobenius norms, not squared; peft exposes no function for it).
- `save_adapter` writes peft's layout (as `PeftModel.save_pretrained` does for AdaLoRA: each layer's
  tensors cut to its kept triplets, `rank_pattern` = the kept mask per `<module>.lora_E`), which
  `peft.PeftModel.from_pretrained(policy, dir)` loads; `merge_adalora` folds the update into the dense
  weights with peft's merge (`lora.merge_lora`).

The schedule's phases are set as fractions of the run's steps (`tinit_fraction`, `tfinal_fraction`), so one
config serves presets of 20 and of 5,000 steps; peft's absolute `tinit`/`tfinal` are derived from them.
`tfinal` is at least 1 step: then the final allocation is forced to exactly target_r per layer on average
and re-applied after every later step, so the saved (pruned) adapter is the trained one.
"""

from __future__ import annotations

import copy
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from pydantic import BaseModel, ConfigDict, Field, model_validator
from torch import nn

from capvector.core.adapters import lora
from capvector.core.adapters.lora import ADAPTER_NAME

if TYPE_CHECKING:
    import peft

SCHEDULE_ATTRIBUTE = "adalora_schedule"


class AdaLoraConfig(BaseModel):
    """AdaLoRA hyper-parameters (peft's, with the schedule's phases as fractions of the run)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)  # alpha, weights: finite numbers

    target_modules: list[str] = Field(
        min_length=1,
        description="nn.Linear modules adapted, by name (module_patterns syntax, as LoRA's target_modules)",
    )
    init_r: int = Field(12, ge=1, description="rank each adapted layer starts with (peft's init_r)")
    target_r: int = Field(
        8, ge=1, description="average rank per layer left once pruning ends (≤ init_r; peft's target_r)"
    )
    alpha: float = Field(
        24.0, description="update scale: ΔW = (alpha / init_r)·B·diag(E)·A (24/12: LoRA's default 16/8)"
    )
    dropout: float = Field(
        0.0, ge=0.0, lt=1.0, description="dropout on the adapter's input, training only (0-1)"
    )
    tinit_fraction: float = Field(
        0.1, ge=0.0, lt=1.0, description="share of the run's steps at the full init_r before pruning starts"
    )
    tfinal_fraction: float = Field(
        0.2,
        ge=0.0,
        lt=1.0,
        description="share of the run's steps at the final allocation, after pruning ends (at least 1 step)",
    )
    delta_t: int = Field(1, ge=1, description="steps between two reallocations while pruning (peft's deltaT)")
    beta1: float = Field(0.85, gt=0.0, lt=1.0, description="EMA factor of the sensitivity scores (0-1)")
    beta2: float = Field(0.85, gt=0.0, lt=1.0, description="EMA factor of their uncertainty (0-1)")
    orth_reg_weight: float = Field(
        0.5, ge=0.0, description="weight of the orthogonal regularizer on A and B (peft's default 0.5)"
    )

    @model_validator(mode="after")
    def _ranks(self) -> AdaLoraConfig:
        if self.target_r > self.init_r:
            raise ValueError(f"adalora.target_r ({self.target_r}) must be ≤ adalora.init_r ({self.init_r})")
        return self

    def schedule(self, total_steps: int) -> tuple[int, int]:
        """peft's (tinit, tfinal) for a run of `total_steps`; an error when no step is left to prune in."""
        tinit = math.floor(self.tinit_fraction * total_steps)
        tfinal = max(1, round(self.tfinal_fraction * total_steps))
        if tinit >= total_steps - tfinal:
            raise ValueError(
                f"adalora: a run of {total_steps} steps has no step to prune ranks in: tinit_fraction "
                f"{self.tinit_fraction:g} gives {tinit} step(s) before pruning and tfinal_fraction "
                f"{self.tfinal_fraction:g} {tfinal} after it (at least 1); lower them or train longer"
            )
        return tinit, tfinal

    def to_peft(self, target_modules: str, total_steps: int) -> peft.AdaLoraConfig:
        import peft

        tinit, tfinal = self.schedule(total_steps)
        return peft.AdaLoraConfig(
            target_modules=target_modules,
            init_r=self.init_r,
            target_r=self.target_r,
            lora_alpha=self.alpha,
            lora_dropout=self.dropout,
            tinit=tinit,
            tfinal=tfinal,
            deltaT=self.delta_t,
            beta1=self.beta1,
            beta2=self.beta2,
            orth_reg_weight=self.orth_reg_weight,
            total_step=total_steps,
        )


class RankSchedule:
    """peft's AdaLoRA tuner as the trainer's `after_optimizer_step` hook, with the rank allocator's state
    (its EMAs and the current rank pattern) as a state dict, so a resumed run allocates as an uninterrupted
    one. A plain object, not an `nn.Module`: kept on the model, it adds nothing to the model's state."""

    def __init__(self, tuner: peft.AdaLoraModel):
        self.tuner = tuner

    @property
    def config(self) -> peft.AdaLoraConfig:
        return self.tuner.peft_config[ADAPTER_NAME]

    def __call__(self, step: int) -> None:
        """peft's `update_and_allocate(step)`: after the optimizer step of 0-based index `step`."""
        self.tuner.update_and_allocate(step)

    def state_dict(self) -> dict[str, Any]:
        allocator = self.tuner.rankallocator
        tensors = {
            field: {k: v.detach().to("cpu").clone() for k, v in getattr(allocator, field).items()}
            for field in ("ipt", "exp_avg_ipt", "exp_avg_unc")
        }
        pattern = self.config.rank_pattern
        tensors["rank_pattern"] = None if pattern is None else {k: list(v) for k, v in pattern.items()}
        return tensors

    def load_state_dict(self, state: dict[str, Any]) -> None:
        allocator = self.tuner.rankallocator
        params = dict(self.tuner.model.named_parameters())
        unknown = sorted({k for f in ("ipt", "exp_avg_ipt", "exp_avg_unc") for k in state[f]} - set(params))
        if unknown:
            raise ValueError(f"AdaLoRA allocator state names parameters this model lacks: {unknown[:3]}")
        for field in ("ipt", "exp_avg_ipt", "exp_avg_unc"):
            moved = {k: v.to(params[k].device, params[k].dtype) for k, v in state[field].items()}
            setattr(allocator, field, moved)
        pattern = state["rank_pattern"]
        self.config.rank_pattern = None if pattern is None else {k: list(v) for k, v in pattern.items()}


def adalora_modules(model: nn.Module) -> dict[str, nn.Module]:
    """The peft AdaLoRA layers (`SVDLinear`) of `model`, by module name."""
    layers = lora.adapter_modules(model)
    if not layers:
        return {}
    from peft.tuners.adalora import SVDLinear

    return {n: m for n, m in layers.items() if isinstance(m, SVDLinear)}


def apply_adalora(model: nn.Module, config: AdaLoraConfig, total_steps: int) -> list[str]:
    """Add peft's AdaLoRA layers to the targeted linear layers, in place (everything else frozen), for a
    run of `total_steps` optimizer steps; `schedule(model)` is the hook to call after each of them."""
    import peft
    from peft.tuners.adalora import SVDLinear

    names = lora.linear_targets(model, config.target_modules)
    peft_config = config.to_peft(lora.peft_targets(model, config.target_modules, names), total_steps)
    with lora.undone_on_error(model):
        tuner = lora.inject(model, peft_config, peft.AdaLoraModel, SVDLinear)
    setattr(model, SCHEDULE_ATTRIBUTE, RankSchedule(tuner))
    return list(adalora_modules(model))


def schedule(model: nn.Module) -> RankSchedule:
    """The rank schedule `apply_adalora` left on `model` (the trainer's after_optimizer_step hook)."""
    found = getattr(model, SCHEDULE_ATTRIBUTE, None)
    if not isinstance(found, RankSchedule):
        raise ValueError("the model has no AdaLoRA rank schedule (apply_adalora adds it)")
    return found


def orthogonality_loss(model: nn.Module) -> torch.Tensor:
    """AdaLoRA's orthogonal regularizer, weighted, as peft's `AdaLoraModel.forward` adds it to `.loss`:
    orth_reg_weight × mean over the A and B matrices of ‖A·Aᵀ − I‖_F, ‖Bᵀ·B − I‖_F (same order and sum)."""
    weight = schedule(model).config.orth_reg_weight
    total, count = 0, 0
    for n, p in model.named_parameters():
        if ("lora_A" in n or "lora_B" in n) and ADAPTER_NAME in n:
            cov = p @ p.T if "lora_A" in n else p.T @ p
            eye = torch.eye(*cov.size(), dtype=cov.dtype, device=cov.device)
            total = total + torch.norm(cov - eye, p="fro")
            count += 1
    if not count:
        raise ValueError("the model has no AdaLoRA A/B matrices")
    return weight * (total / count)


def kept_triplets(model: nn.Module) -> dict[str, torch.Tensor]:
    """Per AdaLoRA layer, the mask (init_r,) of the triplets the allocation keeps (all before any)."""
    pattern = schedule(model).config.rank_pattern or {}
    found = {}
    for name, layer in adalora_modules(model).items():
        mask = pattern.get(f"{name}.lora_E.{ADAPTER_NAME}", pattern.get(f"{name}.lora_E"))
        r = layer.lora_E[ADAPTER_NAME].shape[0]
        found[name] = torch.ones(r, dtype=torch.bool) if mask is None else torch.tensor(mask).bool()
    return found


def ranks(model: nn.Module) -> dict[str, int]:
    """The rank of each AdaLoRA layer now: its kept triplets (peft's rank pattern)."""
    return {name: int(mask.sum()) for name, mask in kept_triplets(model).items()}


def save_adapter(model: nn.Module, out: str | os.PathLike, overwrite: bool = False) -> Path:
    """Save the AdaLoRA adapter in peft's layout, each layer cut to its kept triplets (as
    `PeftModel.save_pretrained` does), so `peft.PeftModel.from_pretrained(policy, out)` loads it."""
    layers = adalora_modules(model)
    if not layers:
        raise ValueError("the model has no AdaLoRA layers to save")
    config = copy.copy(schedule(model).config)
    kept = kept_triplets(model)
    tensors = {}
    for name, layer in layers.items():
        keep = kept[name].to(layer.lora_E[ADAPTER_NAME].device)
        tensors[f"{name}.lora_A"] = layer.lora_A[ADAPTER_NAME][keep]
        tensors[f"{name}.lora_E"] = layer.lora_E[ADAPTER_NAME][keep]
        tensors[f"{name}.lora_B"] = layer.lora_B[ADAPTER_NAME][:, keep]
    if config.rank_pattern is not None:
        config.rank_pattern = {f"{name}.lora_E": mask.tolist() for name, mask in kept.items()}
    return lora.write_peft_adapter(out, tensors, config, overwrite)


def merge_adalora(model: nn.Module) -> nn.Module:
    """Fold the AdaLoRA update into the dense weights with peft's merge and drop the schedule."""
    if hasattr(model, SCHEDULE_ATTRIBUTE):
        delattr(model, SCHEDULE_ATTRIBUTE)
    return lora.merge_lora(model)
