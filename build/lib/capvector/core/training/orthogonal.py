"""The orthogonal regularizer of CapVector: keep downstream updates off γ.

Song et al. (2026), the CapVector paper, §1.4 ("orthogonal loss"): a capability vector γ is the
parameter difference between a model trained with an auxiliary objective and one trained with plain
SFT; when the merged model θ_meta is fine-tuned downstream, the update Δ' = θ − θ_meta is penalised
for overlapping γ entry by entry, so downstream training does not undo the capability γ carries:

    L = λ · Σ_p Σ_ij |γ_ij · Δ'_ij|,    λ = 1e-4 by default (the paper's best).

`OrthogonalRegularizer(model, gamma, meta, ...)` is an `nn.Module` called as `reg(model) -> scalar`
(already weighted), which is what the trainer's `extra_losses` hook expects; any training loop can add it
to its loss. γ (and θ_meta) are stored as buffers on the parameters' device and dtype; parameters
outside the include/exclude filter (`module_patterns` syntax, over γ's tensor names), without a γ tensor,
or frozen are skipped.

Cost: in dense mode the loss is one autograd node over all regularized tensors (`_DenseL1`:
`torch._foreach_*` ops forward, and the gradient written out, λ·γ·sign(γ ⊙ Δ'), in one pass backward)
instead of a sub/mul/norm chain per tensor; tensors whose γ is zero everywhere are left out of the
arithmetic (their term is 0, their gradient an all-zero tensor, as before). Gradients are the
per-tensor expression's bit for bit on float32, and so is the value unless a zero-γ tensor was left
out of the final sum (then equal up to that sum's rounding order); tests/test_orthogonal.py checks
both. The adapter modes keep
one expression per layer (ΔW is built per layer by peft).

Modes:
- `dense` (full fine-tuning): Δ' = θ − θ_meta per parameter tensor.
- `lora_exact`: Δ' is each adapter's dense update, ΔW = s·B·A (materialised per layer through peft's
  `get_delta_weight`, so peft's scaling, rsLoRA and per-layer rank/alpha included; for LoRA-SP the
  merge-time update s·B·diag(σ̄)·A; for AdaLoRA peft's s·B·diag(E)·A, pruned triplets at E = 0), compared
  with γ of that layer's weight (`<module>.weight`). Adapters are peft's LoRA and AdaLoRA layers
  (`lora.apply_lora`, `adalora.apply_adalora`) or LoRA-SP layers; LoRA variants whose update is not
  s·B·A (DoRA) are refused.
- `lora_a`: the cheaper form the paper describes for LoRA, on the A matrices only, independent of B.
  The sources do not say how a full-weight γ (out × in) meets A (r × in); this project defines it
  (inferred) as the entry-wise L1 norm of the projection of γ's rows onto A's rows:

      L_A = λ · Σ_layers Σ_{o,k} |(γ Aᵀ)_{ok}|.

  It is zero exactly when every row of A is orthogonal to every row of γ, i.e. when the input subspace
  the adapter reads from is orthogonal to γ's row space; then ⟨γ, B·A⟩_F = tr(Bᵀ γ Aᵀ) = 0 for every B,
  which is the paper's constraint ⟨γ, Δ'⟩ = 0 (Eq. 6) whatever B learns. Its cost is one (out × in) by
  (in × r) product per layer, like O-LoRA's A-subspace penalty.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping, Sequence
from typing import Literal

import torch
from torch import nn
from torch.autograd.function import once_differentiable

from capvector.core.adapters import lora, lora_sp
from capvector.core.vectors import module_patterns
from capvector.core.vectors.safetensors_io import Checkpoint

Tensors = Mapping[str, torch.Tensor] | str | os.PathLike


def _source(x: Tensors):
    """Names and a getter for a dict of tensors or a safetensors checkpoint (read only what is used)."""
    if isinstance(x, Mapping):
        return list(x), lambda n: x[n]
    ckpt = Checkpoint(x)
    return ckpt.keys(), ckpt.get


def _adapters(model: nn.Module) -> dict[str, nn.Module]:
    """peft LoRA layers and LoRA-SP layers, by module name."""
    return {**lora.adapter_modules(model), **lora_sp.sp_modules(model)}


def _delta(layer: nn.Module) -> torch.Tensor:
    """ΔW of an adapter layer, differentiable in A and B (peft: `get_delta_weight`; LoRA-SP: its merge ΔW)."""
    return layer.delta_weight() if isinstance(layer, lora_sp.LoraSPLinear) else lora.delta_weight(layer)


def _a_matrices(layer: nn.Module) -> list[torch.Tensor]:
    """The A matrices (r × in) the layer reads its input through (one per active peft adapter; AdaLoRA
    keeps A as a bare parameter, LoRA as an `nn.Linear`)."""
    if isinstance(layer, lora_sp.LoraSPLinear):
        return [layer.lora_A.weight]
    found = [layer.lora_A[a] for a in lora.plain_adapters(layer)]
    return [a if isinstance(a, nn.Parameter) else a.weight for a in found]


class _DenseL1(torch.autograd.Function):
    """λ·Σ_p ‖γ_p ⊙ (θ_p − m_p)‖₁ over lists of tensors, as one autograd node.

    The same arithmetic as the per-tensor expression `λ·stack([vector_norm((θ−m)·γ, 1)]).sum()`, in the
    same order: forward `(θ − m)·γ` and one L1 norm per tensor (`torch._foreach_*`), backward the
    gradient the per-tensor graph produces, sign((θ − m)·γ)·γ·(λ·upstream), one pass over the saved
    products instead of three autograd nodes per tensor. `zero` lists the indices of parameters whose
    γ is zero everywhere: no arithmetic, a 0 term, an all-zero gradient (what the per-tensor graph gives).
    """

    @staticmethod
    def forward(ctx, weight: float, gammas: list, metas: list, zero: tuple, *params: torch.Tensor):
        zeros = set(zero)
        live = [p for i, p in enumerate(params) if i not in zeros]
        prods = torch._foreach_sub(live, metas)
        torch._foreach_mul_(prods, gammas)
        norms = torch._foreach_norm(prods, 1, dtype=torch.float32)
        ctx.save_for_backward(*prods)
        ctx.gammas, ctx.weight = gammas, weight
        ctx.zeros = {i: (params[i].shape, params[i].dtype, params[i].device) for i in zeros}
        total = torch.stack(norms).sum() if norms else params[0].new_zeros((), dtype=torch.float32)
        return total * weight

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: torch.Tensor):
        grads = torch._foreach_sign(ctx.saved_tensors)
        torch._foreach_mul_(grads, ctx.gammas)
        torch._foreach_mul_(grads, grad * ctx.weight)
        live = iter(grads)
        out = []
        for i, needed in enumerate(ctx.needs_input_grad[4:]):
            if i in ctx.zeros:
                shape, dtype, device = ctx.zeros[i]
                g = torch.zeros(shape, dtype=dtype, device=device) if needed else None
            else:
                g = next(live)
            out.append(g if needed else None)
        return (None, None, None, None, *out)


class OrthogonalRegularizer(nn.Module):
    """λ·Σ |γ ⊙ Δ'| over the model's parameters (or adapters); see the module docstring."""

    def __init__(
        self,
        model: nn.Module,
        gamma: Tensors,
        meta: Tensors | None = None,
        lambda_absolute: float = 1e-4,
        include: Sequence[str] | None = None,
        exclude: Sequence[str] | None = None,
        mode: Literal["dense", "lora_exact", "lora_a"] = "dense",
    ):
        super().__init__()
        self.lambda_absolute = lambda_absolute
        self.mode = mode
        g_names, g_get = _source(gamma)
        if include or exclude:
            g_names = module_patterns.select(g_names, include, exclude, what="γ tensor")
        g_names = set(g_names)
        if mode == "dense":
            if meta is None:
                raise ValueError("dense mode needs θ_meta (the merged checkpoint training started from)")
            m_names, m_get = _source(meta)
            params = {n: p for n, p in model.named_parameters() if p.requires_grad and p.is_floating_point()}
            self.names = [n for n in params if n in g_names]
            missing = [n for n in self.names if n not in set(m_names)]
            if missing:
                raise ValueError(f"θ_meta lacks {len(missing)} tensor(s) that γ has: {missing[:5]}")
            targets = {n: params[n] for n in self.names}
            sources = {n: (g_get(n), m_get(n)) for n in self.names}
        elif mode in ("lora_exact", "lora_a"):
            mods = _adapters(model)
            self.names = [n for n in mods if f"{n}.weight" in g_names]
            for n in self.names:  # refuse what s·B·A does not describe (DoRA) now, not mid-training
                _a_matrices(mods[n])
            targets = {n: mods[n].base_layer.weight for n in self.names}
            sources = {n: (g_get(f"{n}.weight"), None) for n in self.names}
        else:
            raise ValueError(f"unknown mode {mode!r}")
        if not self.names:
            raise ValueError(
                f"no trainable {'parameter' if mode == 'dense' else 'adapter layer'} of the model has a γ "
                f"tensor (γ has e.g. {sorted(g_names)[:3]})"
            )
        for i, n in enumerate(self.names):
            ref = targets[n]
            g, m = sources[n]
            want = tuple(ref.shape)
            if tuple(g.shape) != want or (m is not None and tuple(m.shape) != want):
                raise ValueError(
                    f"γ/θ_meta for {n!r} has shape {tuple(g.shape)}, the model {tuple(ref.shape)}"
                )
            self.register_buffer(f"gamma_{i}", g.detach().to(ref.device, ref.dtype).clone(), persistent=False)
            if m is not None:
                self.register_buffer(
                    f"meta_{i}", m.detach().to(ref.device, ref.dtype).clone(), persistent=False
                )
        self._bound: tuple[int, list] | None = None
        # tensors whose γ is zero everywhere: term 0 and gradient 0, nothing to compute (dense mode)
        self._zero = tuple(i for i in range(len(self.names)) if not bool(getattr(self, f"gamma_{i}").any()))

    def _targets(self, model: nn.Module) -> list:
        """What the loss reads from `model` (parameters or adapter modules), looked up once per model."""
        if self._bound is None or self._bound[0] != id(model):
            if self.mode == "dense":
                params = dict(model.named_parameters())
                found = [params.get(n) for n in self.names]
            else:
                mods = _adapters(model)
                found = [mods.get(n) for n in self.names]
            if any(f is None for f in found):
                raise ValueError("this model lacks parameters the regularizer was built for")
            self._bound = (id(model), found)
        return self._bound[1]

    def dense_parameters(self, model: nn.Module) -> list[nn.Parameter]:
        """The model's parameters this loss reads (dense mode)."""
        if self.mode != "dense":
            raise ValueError(f"dense_parameters: the regularizer is in {self.mode!r} mode")
        return self._targets(model)

    def gamma_norm(self) -> float:
        """‖γ‖₂ over the regularized tensors."""
        squares = [getattr(self, f"gamma_{i}").double().square().sum() for i in range(len(self.names))]
        return float(torch.stack(squares).sum().sqrt())

    def gradient_ratio(self, model: nn.Module, losses: Iterable[torch.Tensor]) -> float:
        """‖∇ loss‖ / ‖γ‖ over the regularized tensors (dense mode), the loss's gradient norm averaged over
        `losses` (scalars computed on a few training batches at the model as training starts).

        λ in relative form: `lambda_absolute = lambda_relative × this ratio` makes the orthogonal loss's
        gradient, λ·γ ⊙ sign(θ − θ_meta) of norm λ·‖γ‖, that multiple of the action loss's, whatever the
        model's scale or γ's norm. The paper's λ (1e-4) is the absolute form: set `lambda_absolute` to it."""
        params = self.dense_parameters(model)
        norms = []
        for loss in losses:
            grads = torch.autograd.grad(loss, params, allow_unused=True)
            norms.append(torch.linalg.vector_norm(torch.stack([g.norm() for g in grads if g is not None])))
        gamma = self.gamma_norm()
        if gamma == 0:
            raise ValueError("γ is zero on every regularized tensor: no orthogonal loss can be scaled to it")
        if not norms:
            raise ValueError("gradient_ratio needs at least one loss")
        return float(torch.stack(norms).mean()) / gamma

    def forward(self, model: nn.Module) -> torch.Tensor:
        targets = self._targets(model)
        if self.mode == "dense":
            live = [i for i in range(len(self.names)) if i not in self._zero]
            gammas = [getattr(self, f"gamma_{i}") for i in live]
            metas = [getattr(self, f"meta_{i}") for i in live]
            return _DenseL1.apply(self.lambda_absolute, gammas, metas, self._zero, *targets)
        terms = []
        for i, t in enumerate(targets):
            g = getattr(self, f"gamma_{i}")
            if self.mode == "lora_exact":
                d = _delta(t) * g
            else:
                d = g @ torch.cat(_a_matrices(t)).T
            terms.append(torch.linalg.vector_norm(d, 1, dtype=torch.float32))
        return torch.stack(terms).sum() * self.lambda_absolute
