"""LoRA-SP (Kim et al., 2026): rank-adaptive LoRA with input-conditioned singular values over a vector bank.

Per adapted linear layer (the LoRA-SP paper's formulation):
- ΔW(x) = s·U·diag(σ(x))·V, with V = `lora_A` (bank × in), U = `lora_B` (out × bank), s = alpha / bank;
- σ(x) = softplus(router(x)) (or ReLU): a linear router on the layer input gives non-negative scores,
  one per bank vector, acting as data-conditioned singular values;
- per input (token), the scores are sorted and only the smallest k with
  E(k) = Σ_{i≤k} σ_(i)² / Σ_j σ_j² ≥ η is kept; the others are zeroed by a mask (gradients flow through
  the kept scores only). η = 1 keeps the whole bank;
- losses: spectral 1 − E(k) (mean over tokens) with weight 1e-2, and the router term with weight 1e-3:
  Switch-style load balance bank·Σ_j f_j·p_j (f_j share of tokens whose top score is j, p_j mean
  normalised score) plus the ST-MoE z-loss mean(logsumexp(router logits)²). (The authors' code uses a
  clamped log1p form of the z-loss and weight 1e-2 for it; the paper gives one 1e-3 on the router term.)
  Both are averaged over layers by `lora_sp_loss(model)`, which plugs into the trainer's extra-loss hook.

Observability: every module keeps `rank_ema` (running mean of its active rank k during training) and,
since the last `reset_stats()`, the sum of kept score vectors and of k over all tokens seen.

Dense merge: ΔW(x) depends on x, so no single dense matrix reproduces the layer in general.
`lora.merge_lora` (through `LoraSPLinear.merge_into_base`) uses ΔW = s·U·diag(σ̄)·V with σ̄ the mean
masked score vector over the tokens seen since `reset_stats()` (run `calibrate` over representative data
first). When the router ignores the input (weight all zero, scores = activation(bias)), σ̄ is that
constant vector and the merge is exact; otherwise it is the linear layer that matches the adapter's
average update, an approximation.

Saved layout: like LoRA (`adapter_model.safetensors` + `adapter_config.json` with peft's fields) with
peft_type "LORA_SP" (a project type peft does not know), extra tensors `<module>.lora_router.weight/.bias`
and `<module>.lora_stats.{score_sum,token_count,rank_sum}`, `r` = bank size, `target_modules` the peft regex
of the patterns (older files: the pattern list), `rank_pattern` = each module's mean active rank (rounded
up), and the exact means under `active_rank`.

Why not a peft tuner: peft has no LoRA-SP, and its extension point for custom layers
(`LoraConfig._register_custom_module`) is private and experimental, would still need this whole layer, and
the result could not be loaded by a plain peft anyway. So the layer is ours (standalone, peft's attribute
and key names), targets use the same `module_patterns` syntax as LoRA, and `lora.merge_lora` merges it.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Literal

import torch
import torch.nn.functional as F
from pydantic import BaseModel, ConfigDict, Field
from torch import nn

from capvector.core.adapters.lora import (
    PEFT_PREFIX,
    check_tensors,
    linear_targets,
    peft_config_json,
    read_adapter,
    write_adapter,
)
from capvector.core.vectors import module_patterns


class LoraSPConfig(BaseModel):
    """LoRA-SP hyper-parameters; defaults are the paper's (bank 128, alpha 256, η 0.9, 1e-2 / 1e-3)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)  # alpha, weights: finite numbers

    target_modules: list[str] = Field(
        min_length=1,
        description="nn.Linear modules adapted, by name (module_patterns syntax, as LoRA's target_modules)",
    )
    bank_size: int = Field(
        128, ge=1, description="vectors in each layer's bank: the largest rank an input can use"
    )
    alpha: float = Field(256.0, description="update scale: ΔW(x) = (alpha / bank_size)·U·diag(σ(x))·V")
    eta: float = Field(
        0.9,
        gt=0.0,
        le=1.0,
        description="energy kept per input (0-1]: the fewest scores holding this share of Σσ² stay active; "
        "1: the whole bank, lower: smaller ranks",
    )
    dropout: float = Field(
        0.0, ge=0.0, lt=1.0, description="dropout on the adapter's input, training only (0-1)"
    )
    init: Literal["kaiming", "gaussian"] = Field(
        "kaiming", description="how V (lora_A) starts: `kaiming` or `gaussian`; U (lora_B) starts at zero"
    )
    activation: Literal["softplus", "relu"] = Field(
        "softplus", description="router logits -> non-negative singular values σ(x)"
    )
    spectral_weight: float = Field(
        1e-2, description="weight of the spectral loss 1 − E(k), which pushes energy into fewer vectors"
    )
    router_weight: float = Field(1e-3, description="weight of the router's load-balance + z-loss term")
    rank_momentum: float = Field(
        0.01,
        gt=0.0,
        le=1.0,
        description="momentum (0-1] of the running mean of each layer's active rank (monitoring only)",
    )


def select_active(scores: torch.Tensor, eta: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Mask of the kept scores and k per row: the smallest k with E(k) ≥ η over sorted squared scores."""
    r = scores.shape[-1]
    if eta >= 1.0:  # rounding could otherwise drop a tiny last score
        return torch.ones_like(scores, dtype=torch.bool), torch.full(
            scores.shape[:-1], r, device=scores.device
        )
    sq = scores.detach().float().square()
    sorted_sq, order = sq.sort(dim=-1, descending=True)
    energy = sorted_sq.cumsum(-1) / sq.sum(-1, keepdim=True).clamp_min(torch.finfo(torch.float32).tiny)
    k = ((energy < eta).sum(-1) + 1).clamp(max=r)
    keep_sorted = torch.arange(r, device=scores.device) < k.unsqueeze(-1)
    mask = torch.zeros_like(keep_sorted).scatter(-1, order, keep_sorted)
    return mask, k


class LoraSPLinear(nn.Module):
    """y = W₀x + b + s·U·(σ_k(x) ⊙ V·dropout(x)); see the module docstring. W₀ and b frozen.

    A wrapper of our own over `nn.Linear` (peft has no LoRA-SP), with peft's attribute names
    (`base_layer`, `lora_A`, `lora_B`, `lora_dropout`) so the saved keys follow peft's layout.
    """

    def __init__(self, base: nn.Linear, config: LoraSPConfig):
        super().__init__()
        r = config.bank_size
        self.config = config
        self.base_layer = base
        self.scaling = config.alpha / r
        self.eta = config.eta
        self.momentum = config.rank_momentum
        self.activation = F.softplus if config.activation == "softplus" else F.relu
        kw = {"device": base.weight.device, "dtype": base.weight.dtype}
        # (the order of random draws is the one of earlier versions: same seed, same adapter)
        self.lora_A = nn.Linear(base.in_features, r, bias=False, **kw)
        self.lora_B = nn.Linear(r, base.out_features, bias=False, **kw)
        self.lora_dropout = nn.Dropout(config.dropout) if config.dropout > 0 else nn.Identity()
        if config.init == "kaiming":
            nn.init.kaiming_uniform_(self.lora_A.weight, a=math.sqrt(5))
        else:
            nn.init.normal_(self.lora_A.weight, std=1.0 / r)
        nn.init.zeros_(self.lora_B.weight)
        self.lora_router = nn.Linear(base.in_features, r, bias=True, **kw)
        for p in base.parameters():
            p.requires_grad_(False)
        self.register_buffer("rank_ema", torch.tensor(-1.0), persistent=False)
        self.register_buffer("score_sum", torch.zeros(r, dtype=torch.float64), persistent=False)
        self.register_buffer("token_count", torch.tensor(0.0, dtype=torch.float64), persistent=False)
        self.register_buffer("rank_sum", torch.tensor(0.0, dtype=torch.float64), persistent=False)
        self.last_losses: dict[str, torch.Tensor] = {}
        # A (no-op) hook keeps nn.TransformerEncoderLayer off its fused inference path, which would use
        # `.weight` and cannot express an input-dependent update.
        self.register_forward_pre_hook(lambda module, args: None)

    @property
    def in_features(self) -> int:
        return self.base_layer.in_features

    @property
    def out_features(self) -> int:
        return self.base_layer.out_features

    @property
    def weight(self) -> torch.Tensor:
        """The frozen W₀ (ΔW depends on the input; fused paths that read `.weight` are kept off)."""
        return self.base_layer.weight

    @property
    def bias(self) -> torch.Tensor | None:
        return self.base_layer.bias

    @property
    def input_independent(self) -> bool:
        return not bool(self.lora_router.weight.detach().any())

    def scores(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Router logits and non-negative scores σ(x)."""
        logits = self.lora_router(x)
        return logits, self.activation(logits)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        logits, s = self.scores(x)
        mask, k = select_active(s, self.eta)
        kept = s * mask
        out = self.base_layer(x) + self.lora_B(self.lora_A(self.lora_dropout(x)) * kept) * self.scaling
        self._record(logits, s, kept, k)
        return out

    def _record(self, logits, s, kept, k) -> None:
        r = s.shape[-1]
        s2, kept2 = s.reshape(-1, r).float(), kept.reshape(-1, r).float()
        total = s2.square().sum(-1).clamp_min(torch.finfo(torch.float32).tiny)
        spectral = (1.0 - kept2.square().sum(-1) / total).mean()
        probs = s2 / s2.sum(-1, keepdim=True).clamp_min(torch.finfo(torch.float32).tiny)
        top = F.one_hot(s2.argmax(-1), r).float().mean(0)
        balance = r * (top * probs.mean(0)).sum()
        z = torch.logsumexp(logits.reshape(-1, r).float(), dim=-1).square().mean()
        self.last_losses = {"spectral": spectral, "router": balance + z}
        with torch.no_grad():
            kf = k.reshape(-1).double()
            if self.training:
                m = kf.mean().float()
                self.rank_ema.copy_(m if self.rank_ema < 0 else torch.lerp(self.rank_ema, m, self.momentum))
            self.score_sum += kept2.detach().double().sum(0)
            self.token_count += kf.numel()
            self.rank_sum += kf.sum()

    def reset_stats(self) -> None:
        self.score_sum.zero_()
        self.token_count.zero_()
        self.rank_sum.zero_()

    @property
    def mean_active_rank(self) -> float | None:
        """Mean k over the tokens seen since `reset_stats()` (None if none)."""
        n = float(self.token_count)
        return float(self.rank_sum) / n if n else None

    def merge_scores(self) -> torch.Tensor:
        """σ used by the dense merge: exact constant scores if input-independent, else the calibrated mean."""
        if self.input_independent:
            _, s = self.scores(
                torch.zeros(
                    self.in_features, device=self.lora_A.weight.device, dtype=self.lora_A.weight.dtype
                )
            )
            mask, _ = select_active(s, self.eta)
            return (s * mask).float()
        if not float(self.token_count):
            raise RuntimeError("LoRA-SP scores depend on the input: run calibrate() before merging")
        return (self.score_sum / self.token_count).float()

    def delta_weight(self) -> torch.Tensor:
        """s·U·diag(σ)·V with σ from `merge_scores` (differentiable in U and V, not in σ)."""
        sigma = self.merge_scores().to(self.lora_A.weight.dtype)
        return (self.lora_B.weight * sigma) @ self.lora_A.weight * self.scaling

    @torch.no_grad()
    def merge_into_base(self) -> nn.Linear:
        """The base layer holding W₀ + ΔW (computed in float32), for `lora.merge_lora`."""
        base = self.base_layer
        base.weight.copy_((base.weight.float() + self.delta_weight().float()).to(base.weight.dtype))
        return base

    def adapter_tensors(self) -> dict[str, torch.Tensor]:
        """Tensors saved per module, keyed by the suffix after the module name (peft's naming)."""
        return {
            "lora_A.weight": self.lora_A.weight,
            "lora_B.weight": self.lora_B.weight,
            "lora_router.weight": self.lora_router.weight,
            "lora_router.bias": self.lora_router.bias,
            "lora_stats.score_sum": self.score_sum,
            "lora_stats.token_count": self.token_count,
            "lora_stats.rank_sum": self.rank_sum,
        }


def apply_lora_sp(model: nn.Module, config: LoraSPConfig) -> list[str]:
    """Wrap the targeted linear layers (not those inside nn.MultiheadAttention); freeze everything else."""
    names = linear_targets(model, config.target_modules)
    for p in model.parameters():
        p.requires_grad_(False)
    for n in names:
        parent, _, child = n.rpartition(".")
        setattr(
            model.get_submodule(parent) if parent else model,
            child,
            LoraSPLinear(model.get_submodule(n), config),
        )
    return names


def sp_modules(model: nn.Module) -> dict[str, LoraSPLinear]:
    return {n: m for n, m in model.named_modules() if isinstance(m, LoraSPLinear)}


def lora_sp_loss(model: nn.Module) -> torch.Tensor:
    """spectral_weight·mean(1 − E(k)) + router_weight·mean(balance + z) over layers, from the last forward."""
    mods = [m for m in sp_modules(model).values() if m.last_losses]
    if not mods:
        raise RuntimeError("no LoRA-SP layer has run a forward pass yet")
    cfg = mods[0].config
    spectral = torch.stack([m.last_losses["spectral"] for m in mods]).mean()
    router = torch.stack([m.last_losses["router"] for m in mods]).mean()
    return cfg.spectral_weight * spectral + cfg.router_weight * router


def active_ranks(model: nn.Module, since_reset: bool = False) -> dict[str, float]:
    """Per layer: the running mean active rank (training EMA), or the mean since `reset_stats()`."""
    if since_reset:
        return {n: m.mean_active_rank for n, m in sp_modules(model).items() if m.mean_active_rank is not None}
    return {n: float(m.rank_ema) for n, m in sp_modules(model).items() if float(m.rank_ema) >= 0}


@torch.no_grad()
def calibrate(
    model: nn.Module, batches: Iterable, forward: Callable[[nn.Module, object], object] | None = None
):
    """Reset the score statistics and run `forward(model, batch)` (default `model(batch)`) in eval mode."""
    was_training = model.training
    model.eval()
    for m in sp_modules(model).values():
        m.reset_stats()
    try:
        for batch in batches:
            forward(model, batch) if forward else model(batch)
    finally:
        model.train(was_training)


def save_adapter(model: nn.Module, out: str | os.PathLike, overwrite: bool = False) -> Path:
    """Save in peft's layout with peft_type "LORA_SP"; rank_pattern = mean active rank per layer."""
    import peft  # lazily, as in `lora`: only for peft's LoRA config fields

    mods = sp_modules(model)
    if not mods:
        raise ValueError("the model has no LoRA-SP modules")
    config = next(iter(mods.values())).config
    means = active_ranks(model, since_reset=True) or active_ranks(model)
    doc = peft_config_json(
        peft.LoraConfig(
            target_modules=module_patterns.to_peft_regex(config.target_modules),
            r=config.bank_size,
            lora_alpha=config.alpha,
            lora_dropout=config.dropout,
            init_lora_weights=True if config.init == "kaiming" else "gaussian",
            rank_pattern={n: math.ceil(v) for n, v in means.items()},
            inference_mode=True,
        )
    )
    doc.update(
        peft_type="LORA_SP",
        active_rank=means,
        lora_sp=config.model_dump(exclude={"target_modules", "alpha", "dropout"}),
    )
    tensors = {f"{n}.{k}": t for n, m in mods.items() for k, t in m.adapter_tensors().items()}
    return write_adapter(tensors, doc, out, overwrite)


def load_adapter(model: nn.Module, path: str | os.PathLike) -> list[str]:
    """Apply a saved LoRA-SP adapter to `model` (without adapters) and load weights and statistics."""
    doc, tensors = read_adapter(path)
    if doc.get("peft_type") != "LORA_SP":
        raise ValueError(f"{path} holds a {doc.get('peft_type')} adapter, not LORA_SP")
    config = LoraSPConfig(
        target_modules=module_patterns.from_peft(doc["target_modules"]),
        alpha=doc["lora_alpha"],
        dropout=doc.get("lora_dropout", 0.0),
        **doc["lora_sp"],
    )
    names = apply_lora_sp(model, config)
    expected = {
        f"{PEFT_PREFIX}{n}.{k}": t
        for n, m in sp_modules(model).items()
        for k, t in m.adapter_tensors().items()
    }
    check_tensors(expected, tensors)
    with torch.no_grad():
        for k, t in expected.items():
            t.copy_(tensors[k])
    return names
