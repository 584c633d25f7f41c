"""LoRA on chosen `nn.Linear` layers of any `nn.Module`, through peft: peft's layers, layout and loader.

Why peft: it is the library our users already have. `apply_lora` injects peft's LoRA layers in place
(through peft's `LoraModel`, as `peft.inject_adapter_in_model` does; `inject` serves AdaLoRA too);
`save_adapter` writes what `peft.PeftModel.from_pretrained(policy, dir)` loads
(`adapter_model.safetensors` with `base_model.model.<module>.lora_A.weight` (r × in) and
`...lora_B.weight` (out × r), and peft's own `adapter_config.json`); `load_adapter` goes through peft, so
a peft-made adapter's `use_rslora`, `alpha_pattern` and `rank_pattern` give peft's scaling; `merge_lora` folds
each adapter in with peft's own merge, so it equals peft's `merge_and_unload()` tensor for tensor.

Targets are picked with `capvector.core.vectors.module_patterns` (one syntax for every name filter); only real
`nn.Linear` modules count, and a pattern matching none is an error naming it. The saved
`target_modules` is the peft regex of those patterns (`module_patterns.to_peft_regex`), or, when the
patterns also match modules that are not adapted (containers, non-linear layers), the regex of the exact
adapted names, so peft adapts the same modules we did.

Refused: `nn.Linear` children of `nn.MultiheadAttention` (it reads `out_proj.weight` without calling the
layer, so a peft layer there would silently do nothing). Adapted layers inside `nn.TransformerEncoderLayer`
get a no-op forward pre-hook, which keeps that layer off its fused inference path (which reads `.weight`
and would skip the adapter); a model loaded with plain peft does not get it.

peft reads `model.config` as a dict (`to_dict()`), e.g. for `merge_and_unload`; a model whose `config` is
something else is refused here with that reason rather than failing deep inside peft.

An adapter file is untrusted input: `load_adapter` checks it before anything is built (finite alphas and
dropout, positive integer ranks, each lora_A/lora_B shaped as its layer at the config's rank, finite
tensors) and matches its patterns (target/exclude modules, rank/alpha patterns, layers pattern) with
peft's rules but a time budget (`_Matcher`), then gives peft the exact module names found, so a pattern
that backtracks catastrophically is refused in seconds instead of hanging peft's `re.fullmatch`.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import os
import re
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Protocol, runtime_checkable

import torch
from pydantic import BaseModel, ConfigDict, Field
from safetensors.torch import load_file, save_file
from torch import nn

from capvector.core.vectors import module_patterns
from capvector.core.vectors.safetensors_io import atomic_directory

if TYPE_CHECKING:
    import peft
    from peft.tuners.lora import LoraLayer
    from peft.tuners.tuners_utils import BaseTuner

ADAPTER_WEIGHTS = "adapter_model.safetensors"
ADAPTER_CONFIG = "adapter_config.json"
PEFT_PREFIX = "base_model.model."
ADAPTER_NAME = "default"
# peft LoRA features that wrap modules other than nn.Linear (or add trainable non-LoRA state): not loaded.
_UNSUPPORTED = ("modules_to_save", "trainable_token_indices", "target_parameters", "layer_replication")


class LoraConfig(BaseModel):
    """LoRA hyper-parameters; B starts at zero, so an adapted model starts equal to its base."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)  # alpha, weights: finite numbers

    target_modules: list[str] = Field(
        min_length=1,
        description="nn.Linear modules adapted, by name (module_patterns syntax: `attn.*_proj`, `re:...`); "
        "a pattern matching no linear layer is an error",
    )
    r: int = Field(8, ge=1, description="rank of each update B·A; larger: more capacity and parameters")
    alpha: float = Field(16.0, description="update scale: ΔW = (alpha / r)·B·A (alpha/√r with use_rslora)")
    dropout: float = Field(
        0.0, ge=0.0, lt=1.0, description="dropout on the adapter's input, training only (0-1)"
    )
    init: Literal["kaiming", "gaussian"] = Field(
        "kaiming", description="how A starts: `kaiming` (peft's default) or `gaussian`; B starts at zero"
    )
    use_rslora: bool = Field(
        False, description="scale by alpha/√r instead of alpha/r (peft's rsLoRA), steadier across ranks"
    )

    @property
    def scaling(self) -> float:
        return self.alpha / (math.sqrt(self.r) if self.use_rslora else self.r)

    def to_peft(self, target_modules: str) -> peft.LoraConfig:
        import peft

        return peft.LoraConfig(
            target_modules=target_modules,
            r=self.r,
            lora_alpha=self.alpha,
            lora_dropout=self.dropout,
            init_lora_weights=True if self.init == "kaiming" else "gaussian",
            use_rslora=self.use_rslora,
        )


@runtime_checkable
class MergeableAdapter(Protocol):
    """A project adapter over an `nn.Linear` that peft does not know (LoRA-SP): `merge_lora` replaces it
    by `merge_into_base()`, its base layer with the dense update folded in."""

    def merge_into_base(self) -> nn.Linear: ...


def _peft_layer_types() -> tuple[type, type] | None:
    """(LoraLayer, BaseTunerLayer), or None while peft is not imported (then no model has its layers).

    peft is imported only when needed: it imports transformers, seconds of start-up for every command
    that merely reads a `LoraConfig` or loads a LoRA-SP adapter.
    """
    if "peft" not in sys.modules:
        return None
    from peft.tuners.lora import LoraLayer
    from peft.tuners.tuners_utils import BaseTunerLayer

    return LoraLayer, BaseTunerLayer


def adapter_modules(model: nn.Module) -> dict[str, LoraLayer]:
    """The peft LoRA layers of `model`, by module name."""
    types = _peft_layer_types()
    return {n: m for n, m in model.named_modules() if isinstance(m, types[0])} if types else {}


def _own_adapters(model: nn.Module) -> dict[str, nn.Module]:
    return {n: m for n, m in model.named_modules() if isinstance(m, MergeableAdapter)}


def trainable_parameter_count(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def plain_adapters(layer: LoraLayer) -> list[str]:
    """The active adapters of a peft LoRA layer, whose update is s·B·A; variants (DoRA, …) are refused."""
    variants = [a for a in layer.active_adapters if a in getattr(layer, "lora_variant", {})]
    if variants:
        raise ValueError(f"adapter(s) {variants} use a LoRA variant (e.g. DoRA): ΔW is not s·B·A")
    names = [a for a in layer.active_adapters if a in layer.lora_A]
    if not names:
        raise ValueError("this LoRA layer has no active adapter")
    return names


def delta_weight(layer: LoraLayer) -> torch.Tensor:
    """The dense update of a peft LoRA layer (out × in): Σ over its plain active adapters of s·B·A, through
    peft's `get_delta_weight` (differentiable in A and B)."""
    deltas = [layer.get_delta_weight(a) for a in plain_adapters(layer)]
    return deltas[0] if len(deltas) == 1 else torch.stack(deltas).sum(0)


def _inside_adapters(model: nn.Module) -> set[str]:
    """Names of modules that belong to an adapter (its base layer, its A/B/router layers)."""
    types = _peft_layer_types()
    wrappers = (types[1], MergeableAdapter) if types else (MergeableAdapter,)
    inside = set()
    for n, m in model.named_modules():
        if isinstance(m, wrappers):
            inside.update(f"{n}.{c}" if n else c for c, _ in m.named_modules() if c)
    return inside


def _mha_children(model: nn.Module, names: list[str]) -> list[str]:
    mha = {n for n, m in model.named_modules() if isinstance(m, nn.MultiheadAttention)}
    return [n for n in names if n.rpartition(".")[0] in mha]


def linear_targets(model: nn.Module, patterns: list[str]) -> list[str]:
    """Names of the `nn.Linear` modules (outside existing adapters) matched by `patterns`.

    Errors: a pattern that matches none (named), or a match inside `nn.MultiheadAttention`.
    """
    inside = _inside_adapters(model)
    linears = [n for n, m in model.named_modules() if isinstance(m, nn.Linear) and n not in inside]
    dead = module_patterns.dead_patterns(linears, patterns)
    if dead:
        raise ValueError(f"target pattern(s) match no nn.Linear module: {module_patterns.describe(dead)}")
    names = [n for n in linears if module_patterns.matches_any(n, patterns)]
    bad = _mha_children(model, names)
    if bad:
        raise ValueError(
            f"{bad} belong to nn.MultiheadAttention, which reads their weight without calling them: "
            "an adapter there would never act"
        )
    return names


def peft_targets(model: nn.Module, patterns: list[str], names: list[str]) -> str:
    """peft's `target_modules` for `names`: the patterns' regex if it selects exactly them, else the names."""
    regex = module_patterns.to_peft_regex(patterns)
    compiled = re.compile(regex)
    hits = [n for n, _ in model.named_modules() if compiled.fullmatch(n)]
    return regex if hits == names else module_patterns.exact_regex(names)


def _check_peft_config(model: nn.Module) -> None:
    config = getattr(model, "config", None)
    if config is None or hasattr(config, "to_dict") or isinstance(config, dict):
        return
    if not dataclasses.is_dataclass(config):
        raise TypeError(
            f"peft reads model.config as a dict; {type(config).__name__} has no to_dict() "
            "(give it one returning {'model_type': ..., **fields})"
        )


def _replace(model: nn.Module, name: str, new: nn.Module) -> None:
    parent_name, _, child = name.rpartition(".")
    setattr(model.get_submodule(parent_name) if parent_name else model, child, new)


def _keep_off_fused_paths(model: nn.Module) -> None:
    """A no-op pre-hook on adapted layers inside nn.TransformerEncoderLayer disables its fused path."""
    layers = set(map(id, adapter_modules(model).values()))
    for m in model.modules():
        if isinstance(m, nn.TransformerEncoderLayer):
            for c in m.modules():
                if id(c) in layers and not c._forward_pre_hooks:
                    c.register_forward_pre_hook(lambda module, args: None)


def _unwrap(model: nn.Module) -> None:
    """Put every peft LoRA layer's base layer back in its place and drop peft's bookkeeping."""
    for name, m in adapter_modules(model).items():
        _replace(model, name, m.get_base_layer())
    if hasattr(model, "peft_config"):
        del model.peft_config


@contextmanager
def undone_on_error(model: nn.Module) -> Iterator[None]:
    """On an exception, remove injected peft layers and restore which parameters were trainable."""
    flags = [(p, p.requires_grad) for p in model.parameters()]
    try:
        yield
    except BaseException:
        _unwrap(model)
        for p, flag in flags:
            p.requires_grad_(flag)
        raise


def inject(model: nn.Module, config: peft.PeftConfig, tuner: type, layer: type) -> BaseTuner:
    """Inject peft's layers for `config` in place (everything else frozen) and return peft's tuner: what
    `peft.inject_adapter_in_model` does, keeping the tuner (AdaLoRA's rank allocator lives on it).

    `tuner` is peft's model class for the config's type (`peft.LoraModel`, `peft.AdaLoraModel`), `layer` its
    wrapper of `nn.Linear`; anything else it wrapped, or a child of `nn.MultiheadAttention`, is refused.
    Call inside `undone_on_error`."""
    _check_peft_config(model)
    if adapter_modules(model) or _own_adapters(model) or hasattr(model, "peft_config"):
        raise ValueError("the model already has adapters (merge or remove them first)")
    made = tuner(model, config, adapter_name=ADAPTER_NAME)
    layers = adapter_modules(model)
    wrong = [
        f"{n} ({type(m.get_base_layer()).__name__})" for n, m in layers.items() if not isinstance(m, layer)
    ]
    bad = _mha_children(model, list(layers))
    if wrong or bad:
        raise ValueError(
            f"only nn.Linear layers outside nn.MultiheadAttention can be adapted here; got {wrong + bad}"
        )
    _keep_off_fused_paths(model)
    return made


def _inject(model: nn.Module, config: peft.LoraConfig) -> list[str]:
    """Inject peft's LoRA layers in place; the names of the adapted layers. Call inside `undone_on_error`."""
    import peft

    inject(model, config, peft.LoraModel, peft.tuners.lora.Linear)
    return list(adapter_modules(model))


def apply_lora(model: nn.Module, config: LoraConfig) -> list[str]:
    """Add peft LoRA layers to the targeted linear layers, in place; everything else is frozen."""
    names = linear_targets(model, config.target_modules)
    with undone_on_error(model):
        return _inject(model, config.to_peft(peft_targets(model, config.target_modules, names)))


def write_adapter(
    tensors: dict[str, torch.Tensor], config_json: dict, out: str | os.PathLike, overwrite: bool = False
) -> Path:
    """Write adapter tensors (keys without the peft prefix) and a config atomically into directory `out`."""
    tensors = {PEFT_PREFIX + k: t.detach().to("cpu").contiguous() for k, t in tensors.items()}
    with atomic_directory(out, overwrite) as tmp:
        save_file(tensors, tmp / ADAPTER_WEIGHTS, metadata={"format": "pt"})
        (tmp / ADAPTER_CONFIG).write_text(json.dumps(config_json, indent=2, sort_keys=True))
    return Path(out)


def peft_config_json(config: peft.LoraConfig) -> dict:
    """`adapter_config.json` as peft writes it (`PeftConfig.save_pretrained`), as a dict."""
    doc = config.to_dict()
    doc.pop("runtime_config", None)  # peft does not save it either
    return json.loads(json.dumps(doc, default=lambda v: sorted(v) if isinstance(v, set) else str(v)))


def save_adapter(model: nn.Module, out: str | os.PathLike, overwrite: bool = False) -> Path:
    """Save the LoRA adapter in peft's layout. LoRA-SP models: use `lora_sp.save_adapter`."""
    if not adapter_modules(model):
        if _own_adapters(model):
            raise TypeError(
                "these are not peft LoRA adapters; save them with their own module's save_adapter"
            )
        raise ValueError("the model has no adapter modules to save")
    configs = getattr(model, "peft_config", {})
    if set(configs) != {ADAPTER_NAME}:
        raise ValueError(f"expected one adapter named {ADAPTER_NAME!r}, found {sorted(configs)}")
    if configs[ADAPTER_NAME].peft_type != "LORA":
        raise TypeError(
            f"this is a {configs[ADAPTER_NAME].peft_type} adapter; save AdaLoRA with adalora.save_adapter"
        )
    import peft

    tensors = peft.get_peft_model_state_dict(model, adapter_name=ADAPTER_NAME)
    return write_peft_adapter(out, tensors, configs[ADAPTER_NAME], overwrite)


def write_peft_adapter(
    out: str | os.PathLike, tensors: dict[str, torch.Tensor], config: Any, overwrite: bool = False
) -> Path:
    """`out` in peft's layout (weights under peft's key prefix, `adapter_config.json` for inference),
    written atomically: what `PeftModel.from_pretrained` loads. `config` is copied, not changed."""
    config = copy.copy(config)
    config.inference_mode = True
    with atomic_directory(out, overwrite) as tmp:
        save_file(
            {PEFT_PREFIX + k: t.detach().to("cpu").contiguous() for k, t in tensors.items()},
            tmp / ADAPTER_WEIGHTS,
            metadata={"format": "pt"},
        )
        config.save_pretrained(str(tmp))
    return Path(out)


def read_adapter(path: str | os.PathLike) -> tuple[dict, dict[str, torch.Tensor]]:
    """An adapter directory's config (as a dict) and tensors (keys as stored)."""
    path = Path(path)
    for f in (ADAPTER_CONFIG, ADAPTER_WEIGHTS):
        if not (path / f).exists():
            raise FileNotFoundError(f"{path} has no {f}")
    return json.loads((path / ADAPTER_CONFIG).read_text()), load_file(path / ADAPTER_WEIGHTS)


def check_tensors(expected: dict[str, torch.Tensor], tensors: dict[str, torch.Tensor]) -> None:
    """Saved adapter tensors must have exactly the expected keys and shapes; raise naming a few."""
    missing, extra = sorted(expected.keys() - tensors.keys()), sorted(tensors.keys() - expected.keys())
    if missing or extra:
        raise ValueError(f"adapter does not fit the model: missing {missing[:5]}, unexpected {extra[:5]}")
    bad = [
        f"{k} {tuple(tensors[k].shape)} vs {tuple(t.shape)}"
        for k, t in expected.items()
        if t.shape != tensors[k].shape
    ]
    if bad:
        raise ValueError(f"adapter tensors with other shapes (file vs model): {bad[:5]}")


def _has_our_syntax(targets) -> bool:
    return isinstance(targets, list) and any(
        t.startswith(module_patterns.REGEX_PREFIX) or any(c in t for c in "*?[") for t in targets
    )


# An adapter file is checked before anything is built from it: its patterns are matched with a time budget,
# its numbers must be finite and its ranks and shapes must be those of its tensors.
MAX_PATTERN_CHARS = 100_000  # an exact regex of a few thousand module names fits
MATCH_SECONDS = 2.0  # for one pattern against all of the model's module names (legitimate ones: milliseconds)
TOTAL_MATCH_SECONDS = 20.0  # for all of one adapter file's patterns


def _shown(pattern: str, k: int = 80) -> str:
    text = repr(pattern)
    return text if len(text) <= k else text[: k - 1] + "…"


class _Matcher:
    """An adapter file's regexes matched against module names without hanging on them.

    Python's `re` (what peft uses) backtracks: `(a+)+$` against a long name of a's runs for hours. Here
    they run on the `regex` engine (a dependency of transformers, so present with peft; `re`'s syntax and
    semantics), with a time budget per pattern (`MATCH_SECONDS`, over all names) and per file
    (`TOTAL_MATCH_SECONDS`); a pattern that exceeds either is refused, naming it. peft is then handed
    only the exact names found (see `_adapter_targets`), so it never runs the file's own patterns."""

    def __init__(self, path: str | os.PathLike):
        import regex

        self.engine = regex
        self.path = path
        self.end = time.monotonic() + TOTAL_MATCH_SECONDS
        self.compiled: dict[str, object] = {}
        self.spent: dict[str, float] = {}

    def _pattern(self, field: str, pattern: str, shown: str):
        if pattern not in self.compiled:
            if len(pattern) > MAX_PATTERN_CHARS:
                raise ValueError(
                    f"{self.path}: {field} pattern {_shown(shown)} is {len(pattern):,} characters long "
                    f"(at most {MAX_PATTERN_CHARS:,})"
                )
            try:
                self.compiled[pattern] = self.engine.compile(pattern)
            except (self.engine.error, OverflowError, RecursionError) as e:
                raise ValueError(
                    f"{self.path}: {field} pattern {_shown(shown)} is not a valid regex: {e}"
                ) from None
        return self.compiled[pattern]

    def __call__(self, field: str, pattern: str, name: str, shown: str | None = None, full: bool = True):
        """`re.fullmatch(pattern, name)` (`re.match` if not `full`), refusing a pattern that runs too long."""
        shown = pattern if shown is None else shown
        compiled = self._pattern(field, pattern, shown)
        start = time.monotonic()
        own, total = MATCH_SECONDS - self.spent.get(pattern, 0.0), self.end - start
        try:
            return (compiled.fullmatch if full else compiled.match)(name, timeout=max(min(own, total), 1e-3))
        except TimeoutError:
            limit = (
                f"over {MATCH_SECONDS:g} s"
                if own <= total
                else f"the file's last of {TOTAL_MATCH_SECONDS:g} s"
            )
            raise ValueError(
                f"{self.path}: {field} pattern {_shown(shown)} takes {limit} to match the model's module "
                "names (it backtracks catastrophically); refused"
            ) from None
        finally:
            self.spent[pattern] = self.spent.get(pattern, 0.0) + time.monotonic() - start


def _is_int(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _is_number(x) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def _check_numbers(doc: dict, path: str | os.PathLike) -> None:
    """Ranks positive integers, alphas and dropout finite numbers (JSON `NaN`/`Infinity` parse as floats)."""
    bad = []
    if not (_is_int(doc.get("r")) and doc["r"] >= 1):
        bad.append(f"r={doc.get('r')!r} (a positive integer)")
    if not _is_number(doc.get("lora_alpha")):
        bad.append(f"lora_alpha={doc.get('lora_alpha')!r} (a finite number)")
    dropout = doc.get("lora_dropout", 0.0)
    if not (_is_number(dropout) and 0 <= dropout < 1):
        bad.append(f"lora_dropout={dropout!r} (a finite number in [0, 1))")
    for field, ok, what in (
        ("rank_pattern", lambda v: _is_int(v) and v >= 1, "positive integers"),
        ("alpha_pattern", _is_number, "finite numbers"),
    ):
        pattern = doc.get(field) or {}
        if not isinstance(pattern, dict) or not all(isinstance(k, str) for k in pattern):
            bad.append(f"{field} (a mapping of patterns to {what})")
        else:
            bad += [f"{field}[{k!r}]={v!r} ({what[:-1]})" for k, v in pattern.items() if not ok(v)]
    targets = doc.get("target_modules")
    if not (
        isinstance(targets, str) or (isinstance(targets, list) and all(isinstance(t, str) for t in targets))
    ):
        bad.append(f"target_modules={_shown(str(targets))} (a regex or a list of names)")
    if bad:
        raise ValueError(f"{path}: {ADAPTER_CONFIG} has invalid value(s): {'; '.join(bad)}")


def _layer_index(config: peft.LoraConfig, name: str, match: _Matcher) -> int | None:
    """peft's layer index of a module name for `layers_to_transform` (its own two regexes)."""
    patterns = config.layers_pattern
    if not patterns:
        found = match("layers_pattern", r".*?\.[^.]*\.(?P<idx>\d+)\.", name, full=False)
    else:
        found = None
        for p in [patterns] if isinstance(patterns, str) else patterns:
            found = match("layers_pattern", rf"(?:^|.*?\.){p}\.(?P<idx>\d+)\.", name, p, full=False)
            if found is not None:
                break
    return int(found.group("idx")) if found is not None else None


def _peft_targeted(config: peft.LoraConfig, name: str, match: _Matcher) -> bool:
    """peft's `check_target_module_exists` for a LoRA config, with the patterns run by `match`."""
    exclude = config.exclude_modules
    if exclude:
        if isinstance(exclude, str):
            if match("exclude_modules", exclude, name):
                return False
        elif name in exclude or any(name.endswith(f".{e}") for e in exclude):
            return False
    targets = config.target_modules
    if isinstance(targets, str):
        return match("target_modules", targets, name) is not None
    if name in targets:
        return True
    if not any(name.endswith(f".{t}") for t in targets):
        return False
    layers = config.layers_to_transform
    if layers is None or (isinstance(layers, list) and not layers):
        return True
    index = _layer_index(config, name, match)
    return index is not None and (index == layers if isinstance(layers, int) else index in layers)


def _pattern_value(patterns: dict, default, name: str, field: str, match: _Matcher):
    r"""peft's `get_pattern_key`: the value of the first key whose `(.*\.)?(key)$` matches the name."""
    for key, value in patterns.items():
        if match(field, rf"(.*\.)?({key})$", name, key, full=False):
            return value
    return default


def _adapter_targets(
    model: nn.Module, doc: dict, config: peft.LoraConfig, path
) -> dict[str, tuple[nn.Linear, int]]:
    """The modules an adapter file adapts in `model`: those its (guarded) patterns select, all of which
    must be `nn.Linear` outside `nn.MultiheadAttention`."""
    match = _Matcher(path)
    modules = {n: m for n, m in model.named_modules() if n}
    if _has_our_syntax(doc["target_modules"]):  # older capvector adapters: this project's pattern syntax
        patterns = doc["target_modules"]
        try:
            regexes = {p: module_patterns.pattern_regex(p) for p in patterns}
        except module_patterns.PatternError as e:
            raise ValueError(f"{path}: {e}") from None
        linears = [n for n, m in modules.items() if isinstance(m, nn.Linear)]
        hits = {p: {n for n in linears if match("target_modules", rx, n, p)} for p, rx in regexes.items()}
        dead = [p for p, h in hits.items() if not h]
        if dead:
            raise ValueError(f"target pattern(s) match no nn.Linear module: {module_patterns.describe(dead)}")
        names = [n for n in linears if any(n in h for h in hits.values())]
    else:
        names = [n for n in modules if _peft_targeted(config, n, match)]
    if not names:
        raise ValueError(
            f"{path}: target_modules {_shown(str(doc['target_modules']))} match no module of the model"
        )
    wrong = [f"{n} ({type(modules[n]).__name__})" for n in names if not isinstance(modules[n], nn.Linear)]
    bad = _mha_children(model, names)
    if wrong or bad:
        raise ValueError(
            "only nn.Linear layers outside nn.MultiheadAttention can be adapted here; "
            f"got {(wrong + bad)[:5]}"
        )
    ranks = {n: _pattern_value(config.rank_pattern or {}, config.r, n, "rank_pattern", match) for n in names}
    alphas = {
        n: _pattern_value(config.alpha_pattern or {}, config.lora_alpha, n, "alpha_pattern", match)
        for n in names
    }
    config.target_modules = module_patterns.exact_regex(names)
    config.exclude_modules = config.layers_to_transform = config.layers_pattern = None
    # every name its own key, longest first: peft takes the first key matching `(.*\.)?(key)$`
    order = sorted(names, key=len, reverse=True)
    config.rank_pattern = {re.escape(n): ranks[n] for n in order} if config.rank_pattern else {}
    config.alpha_pattern = {re.escape(n): alphas[n] for n in order} if config.alpha_pattern else {}
    return {n: (modules[n], ranks[n]) for n in names}


def _check_tensors_fit(targets: dict, tensors: dict[str, torch.Tensor], path) -> None:
    """Each adapted layer's lora_A (r × in) and lora_B (out × r) are in the file with the layer's shape and
    the config's rank for it, finite; no A/B for other modules. (Other keys are checked after building.)"""
    problems, seen = [], set()
    for name, (layer, r) in targets.items():
        for part, want in (("lora_A", (r, layer.in_features)), ("lora_B", (layer.out_features, r))):
            key = f"{PEFT_PREFIX}{name}.{part}.weight"
            seen.add(key)
            t = tensors.get(key)
            if t is None:
                problems.append(f"missing {key}")
            elif tuple(t.shape) != want:
                problems.append(f"{key} is {list(t.shape)}, the config and layer need {list(want)} (r={r})")
            elif not t.is_floating_point() or not bool(torch.isfinite(t).all()):
                problems.append(f"{key} is not finite floats ({t.dtype})")
    extra = sorted(k for k in tensors if k not in seen and re.search(r"\.lora_[AB]\.weight$", k))
    problems += [f"unexpected {k} (a module the config does not target)" for k in extra]
    if problems:
        more = f" (+{len(problems) - 3} more)" if len(problems) > 3 else ""
        raise ValueError(
            f"{path}: adapter tensors do not fit its config and the model's layer shapes: "
            f"{'; '.join(problems[:3])}{more}"
        )


def load_adapter(model: nn.Module, path: str | os.PathLike) -> list[str]:
    """Apply a saved peft LoRA adapter to `model` (a model without adapters) through peft and load it.

    The adapters are trainable afterwards (as after `apply_lora`). Older capvector adapters whose
    `target_modules` is a list of globs are read with this project's pattern syntax. Before anything is
    built, the file is checked: finite numbers, patterns that match in bounded time (`_Matcher`), every
    target an `nn.Linear`, and each tensor's shape that of its layer at the config's rank; peft then gets
    the exact names found, with their ranks and alphas.
    """
    import peft

    doc, tensors = read_adapter(path)
    kind = doc.get("peft_type")
    if kind != "LORA":
        hint = {
            "LORA_SP": "; use capvector.core.adapters.lora_sp.load_adapter",
            "ADALORA": "; load AdaLoRA with peft.PeftModel.from_pretrained",
        }.get(kind, "")
        raise ValueError(f"{path} holds a {kind} adapter; this loads peft LoRA (LORA) adapters only{hint}")
    _check_numbers(doc, path)
    config = peft.LoraConfig.from_pretrained(str(path))
    used = [f for f in _UNSUPPORTED if getattr(config, f, None)]
    if used:
        raise ValueError(f"{path}: peft LoRA option(s) {used} are not supported here")
    config.inference_mode = False
    _check_peft_config(model)
    if adapter_modules(model) or _own_adapters(model) or hasattr(model, "peft_config"):
        raise ValueError("the model already has adapters (merge or remove them first)")
    _check_tensors_fit(_adapter_targets(model, doc, config, path), tensors, path)
    with undone_on_error(model):
        names = _inject(model, config)
        state = {k.removeprefix(PEFT_PREFIX): t for k, t in tensors.items()}
        check_tensors(peft.get_peft_model_state_dict(model, adapter_name=ADAPTER_NAME), state)
        peft.set_peft_model_state_dict(model, state, adapter_name=ADAPTER_NAME)
    return names


@torch.no_grad()
def merge_lora(model: nn.Module) -> nn.Module:
    """Fold every adapter into its base `nn.Linear` and unwrap it, in place (peft's merge for peft layers,
    `merge_into_base` for LoRA-SP), so the model has its original module names and keys (vectors can be
    taken from LoRA runs) and, like a freshly built model, all parameters trainable."""
    for name, m in adapter_modules(model).items():
        m.merge()
        _replace(model, name, m.get_base_layer())
    for name, m in _own_adapters(model).items():
        _replace(model, name, m.merge_into_base())
    _unwrap(model)
    for p in model.parameters():
        p.requires_grad_(True)
    return model
