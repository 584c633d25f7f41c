"""LoRA adapters on chosen linear layers of any `nn.Module`, saved in the peft layout, mergeable to dense.

Targets are `nn.Linear` modules picked by name patterns, peft style: a pattern matches a module name when
it matches the whole name as a shell glob (`backbone.blocks.*.attn.qkv`), or matches its trailing dotted
components (`qkv` matches `backbone.blocks.0.attn.qkv`); `re:` prefixes a regular expression on the whole
name. A pattern that matches no linear layer is an error, naming it.

Only real `nn.Linear` modules are adapted. `nn.MultiheadAttention` keeps its q/k/v projection in a bare
`in_proj_weight` parameter, which cannot be targeted; its `out_proj` is an `nn.Linear` that the attention
reads through `.weight` without calling it, so the wrapper exposes the effective `weight` (W + s·B·A) and
`bias`: LoRA on `out_proj`, and PyTorch's fused inference path of `nn.TransformerEncoderLayer`, both
see the adapted weights.

Saved layout (peft): `adapter_model.safetensors` with keys `base_model.model.<module>.lora_A.weight`
(r × in) and `...lora_B.weight` (out × r), and `adapter_config.json` with peft's fields.
"""

from __future__ import annotations

import fnmatch
import json
import math
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import torch
from pydantic import BaseModel, ConfigDict, Field
from safetensors.torch import load_file, save_file
from torch import nn

from capvector_core.safetensors_io import atomic_directory

ADAPTER_WEIGHTS = "adapter_model.safetensors"
ADAPTER_CONFIG = "adapter_config.json"
PEFT_PREFIX = "base_model.model."


class LoraConfig(BaseModel):
    """LoRA hyper-parameters; B starts at zero, so an adapted model starts equal to its base."""

    model_config = ConfigDict(extra="forbid")

    target_modules: list[str] = Field(min_length=1)
    r: int = Field(8, ge=1)
    alpha: float = 16.0
    dropout: float = Field(0.0, ge=0.0, lt=1.0)
    init: Literal["kaiming", "gaussian"] = "kaiming"  # how A starts (peft's default / `gaussian`)

    @property
    def scaling(self) -> float:
        return self.alpha / self.r


def module_matches(name: str, pattern: str) -> bool:
    if pattern.startswith("re:"):
        return re.fullmatch(pattern[3:], name) is not None
    return fnmatch.fnmatchcase(name, pattern) or fnmatch.fnmatchcase(name, "*." + pattern)


class LoraLinear(nn.Module):
    """y = W₀x + b + s·B·A·dropout(x), s = alpha / r; W₀ and b frozen."""

    def __init__(self, base: nn.Linear, config: LoraConfig, r: int | None = None):
        super().__init__()
        r = r or config.r
        self.config = config
        self.base_layer = base
        self.scaling = config.alpha / r
        kw = {"device": base.weight.device, "dtype": base.weight.dtype}
        self.lora_A = nn.Linear(base.in_features, r, bias=False, **kw)
        self.lora_B = nn.Linear(r, base.out_features, bias=False, **kw)
        self.lora_dropout = nn.Dropout(config.dropout) if config.dropout > 0 else nn.Identity()
        if config.init == "kaiming":
            nn.init.kaiming_uniform_(self.lora_A.weight, a=math.sqrt(5))
        else:
            nn.init.normal_(self.lora_A.weight, std=1.0 / r)
        nn.init.zeros_(self.lora_B.weight)
        for p in base.parameters():
            p.requires_grad_(False)

    @property
    def in_features(self) -> int:
        return self.base_layer.in_features

    @property
    def out_features(self) -> int:
        return self.base_layer.out_features

    def delta_weight(self) -> torch.Tensor:
        """The dense update s·B·A (out × in), differentiable in A and B."""
        return (self.lora_B.weight @ self.lora_A.weight) * self.scaling

    @property
    def weight(self) -> torch.Tensor:
        return self.base_layer.weight + self.delta_weight().to(self.base_layer.weight.dtype)

    @property
    def bias(self) -> torch.Tensor | None:
        return self.base_layer.bias

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.base_layer(x) + self.lora_B(self.lora_A(self.lora_dropout(x))) * self.scaling

    def adapter_tensors(self) -> dict[str, torch.Tensor]:
        """Tensors saved per module, keyed by the suffix after the module name."""
        return {"lora_A.weight": self.lora_A.weight, "lora_B.weight": self.lora_B.weight}


def find_targets(model: nn.Module, patterns: list[str], forbid_in_mha: bool = False) -> list[str]:
    """Names of the `nn.Linear` modules matched by `patterns`; error on patterns that match none."""
    inside_adapter = {
        f"{n}.{c}"
        for n, m in model.named_modules()
        if isinstance(m, LoraLinear)
        for c, _ in m.named_modules()
        if c
    }
    linears = [n for n, m in model.named_modules() if isinstance(m, nn.Linear) and n not in inside_adapter]
    dead = [p for p in patterns if not any(module_matches(n, p) for n in linears)]
    if dead:
        raise ValueError(f"target pattern(s) match no nn.Linear module: {', '.join(map(repr, dead))}")
    names = [n for n in linears if any(module_matches(n, p) for p in patterns)]
    if forbid_in_mha:
        mha = {n for n, m in model.named_modules() if isinstance(m, nn.MultiheadAttention)}
        bad = [n for n in names if n.rpartition(".")[0] in mha]
        if bad:
            raise ValueError(
                f"{bad} belong to nn.MultiheadAttention, which reads their weight directly: "
                "an input-dependent adapter cannot act there"
            )
    return names


def _replace(model: nn.Module, name: str, new: nn.Module) -> None:
    parent_name, _, child = name.rpartition(".")
    setattr(model.get_submodule(parent_name) if parent_name else model, child, new)


def wrap_linears(model: nn.Module, names: list[str], factory: Callable[[nn.Linear], nn.Module]) -> list[str]:
    """Replace the named linear layers by `factory(layer)` and freeze everything but the adapters."""
    for p in model.parameters():
        p.requires_grad_(False)
    for n in names:
        _replace(model, n, factory(model.get_submodule(n)))
    return names


def apply_lora(model: nn.Module, config: LoraConfig) -> list[str]:
    """Wrap the targeted linear layers in place; everything else is frozen (peft semantics)."""
    names = find_targets(model, config.target_modules)
    return wrap_linears(model, names, lambda lin: LoraLinear(lin, config))


def adapter_modules(model: nn.Module) -> dict[str, LoraLinear]:
    return {n: m for n, m in model.named_modules() if isinstance(m, LoraLinear)}


def trainable_parameter_count(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def peft_config(config: LoraConfig, peft_type: str = "LORA", **extra) -> dict:
    """peft's `adapter_config.json` fields for `config` (plus project fields in `extra`)."""
    return {
        "peft_type": peft_type,
        "task_type": None,
        "base_model_name_or_path": None,
        "r": config.r,
        "lora_alpha": config.alpha,
        "lora_dropout": config.dropout,
        "target_modules": list(config.target_modules),
        "bias": "none",
        "fan_in_fan_out": False,
        "init_lora_weights": True if config.init == "kaiming" else "gaussian",
        "modules_to_save": None,
        "layers_to_transform": None,
        "rank_pattern": {},
        "alpha_pattern": {},
        "use_rslora": False,
        "use_dora": False,
        "inference_mode": True,
        **extra,
    }


def write_adapter(
    model: nn.Module, out: str | os.PathLike, config_json: dict, overwrite: bool = False
) -> Path:
    """Write every adapter module's tensors and `config_json` atomically into directory `out`."""
    mods = adapter_modules(model)
    if not mods:
        raise ValueError("the model has no adapter modules to save")
    tensors = {
        f"{PEFT_PREFIX}{n}.{k}": t.detach().to("cpu").contiguous()
        for n, m in mods.items()
        for k, t in m.adapter_tensors().items()
    }
    with atomic_directory(out, overwrite) as tmp:
        save_file(tensors, tmp / ADAPTER_WEIGHTS, metadata={"format": "pt"})
        (tmp / ADAPTER_CONFIG).write_text(json.dumps(config_json, indent=2))
    return Path(out)


def save_adapter(model: nn.Module, out: str | os.PathLike, overwrite: bool = False) -> Path:
    """Save LoRA adapters (peft layout). LoRA-SP models: use `lora_sp.save_adapter`."""
    configs = {id(m.config): m.config for m in adapter_modules(model).values()}
    if len(configs) != 1:
        raise ValueError(f"expected the adapters of one LoraConfig, found {len(configs)}")
    (config,) = configs.values()
    if not isinstance(config, LoraConfig):
        raise TypeError("these are not plain LoRA adapters; save them with their own module's save_adapter")
    return write_adapter(model, out, peft_config(config), overwrite)


def read_adapter(path: str | os.PathLike) -> tuple[dict, dict[str, torch.Tensor]]:
    path = Path(path)
    for f in (ADAPTER_CONFIG, ADAPTER_WEIGHTS):
        if not (path / f).exists():
            raise FileNotFoundError(f"{path} has no {f}")
    return json.loads((path / ADAPTER_CONFIG).read_text()), load_file(path / ADAPTER_WEIGHTS)


def load_adapter_tensors(model: nn.Module, tensors: dict[str, torch.Tensor]) -> None:
    """Copy saved adapter tensors into the model's adapter modules; keys and shapes must match exactly."""
    expected = {
        f"{PEFT_PREFIX}{n}.{k}": t
        for n, m in adapter_modules(model).items()
        for k, t in m.adapter_tensors().items()
    }
    missing, extra = sorted(expected.keys() - tensors.keys()), sorted(tensors.keys() - expected.keys())
    if missing or extra:
        raise ValueError(f"adapter does not fit the model: missing {missing[:5]}, unexpected {extra[:5]}")
    bad = [k for k, t in expected.items() if t.shape != tensors[k].shape]
    if bad:
        raise ValueError(f"adapter tensors with other shapes: {bad[:5]}")
    with torch.no_grad():
        for k, t in expected.items():
            t.copy_(tensors[k])


def config_from_peft(doc: dict) -> LoraConfig:
    return LoraConfig(
        target_modules=doc["target_modules"],
        r=doc["r"],
        alpha=doc["lora_alpha"],
        dropout=doc.get("lora_dropout", 0.0),
        init="gaussian" if doc.get("init_lora_weights") == "gaussian" else "kaiming",
    )


def load_adapter(model: nn.Module, path: str | os.PathLike) -> list[str]:
    """Apply the saved LoRA adapter to `model` (a model without adapters) and load its weights."""
    doc, tensors = read_adapter(path)
    if doc.get("peft_type") != "LORA":
        raise ValueError(f"{path} holds a {doc.get('peft_type')} adapter; use its own module's load_adapter")
    if doc.get("bias", "none") != "none":
        raise ValueError("only bias='none' adapters are supported")
    names = apply_lora(model, config_from_peft(doc))
    load_adapter_tensors(model, tensors)
    return names


@torch.no_grad()
def merge_lora(model: nn.Module) -> nn.Module:
    """Replace every adapter by its base `nn.Linear` holding W₀ + ΔW (computed in float32), in place.

    The result has the original module names and keys (so vectors can be taken from LoRA runs) and, like
    a freshly built model, all parameters trainable.
    """
    for name, m in adapter_modules(model).items():
        base = m.base_layer  # reuse the original module (its class, e.g. MHA's out_proj, is kept)
        base.weight.copy_((base.weight.float() + m.delta_weight().float()).to(base.weight.dtype))
        _replace(model, name, base)
    for p in model.parameters():
        p.requires_grad_(True)
    return model
