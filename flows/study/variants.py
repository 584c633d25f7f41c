"""A study's arm variants: named arms from θ_pt with config overrides and an lr grid of their own.

A variant (`study.variants: {lora_r4: {arm: sft_lora, set: {lora.r: 4}, lrs: [...]}}`) is one of the
fine-tuning forms that need no γ (full, LoRA, LoRA-SP, AdaLoRA) at one setting. Its `set` is written in the
`--set` syntax (`capvector.flows.recipe.overrides.apply_overrides`, the project's one override syntax), so a
variant means what `--set lora.r=4` would; each is checked when the study is loaded, naming the variant and
key. A variant runs like `sft`: shared by every draw, one run per seed, kept at every budget, its lr chosen
on validation goals at the tuning seeds at the primary endpoint, and compared against `sft`.
"""

from __future__ import annotations

import json
import re
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, ValidationError, field_validator

from capvector.flows.recipe.config import ARMS, PipelineConfig
from capvector.flows.recipe.overrides import apply_overrides

VariantArm = Literal["sft", "sft_lora", "sft_lora_sp", "sft_adalora"]
"""The arms a variant may take: from θ_pt, with no auxiliary objective and no γ."""
NAME = re.compile(r"[a-z][a-z0-9_]*")
FIXED = ("steps", "lr", "seed", "snapshot_steps")
"""downstream keys a variant may not set: the budgets, the lr grid and the seeds are the study's."""


class Variant(BaseModel):
    """One arm at one setting: `arm`'s form with the `set` overrides (dotted key -> value), its lr chosen
    from `lrs` on validation goals."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    arm: VariantArm = Field(description="its form: sft (full), sft_lora, sft_lora_sp or sft_adalora")
    set: dict[str, Any] = Field(
        default_factory=dict,
        description="overrides in the --set syntax, e.g. {lora.r: 4}; only the arm's adapter section "
        "(lora, lora_sp, adalora) and downstream settings other than steps, lr, seed, snapshot_steps",
    )
    lrs: list[PositiveFloat] = Field(min_length=1, description="the lr grid, chosen on validation goals")

    @field_validator("lrs")
    @classmethod
    def _distinct(cls, lrs: list[float]) -> list[float]:
        if len(set(lrs)) != len(lrs):
            raise ValueError(f"repeated values: {lrs}")
        return lrs

    @property
    def section(self) -> str | None:
        """The config section holding this variant's adapter settings (None: full fine-tuning)."""
        adapter = ARMS[self.arm].adapter
        return None if adapter == "full" else adapter


def overrides(variant: Variant) -> list[str]:
    """The variant's `set` as `--set` strings (values as JSON, which the override parser reads as YAML)."""
    return [f"{key}={json.dumps(value)}" for key, value in variant.set.items()]


def _check_keys(name: str, variant: Variant) -> None:
    """Only keys that change the variant's own fine-tuning: its adapter section, or downstream's
    settings other than the study's budgets, lr grid and seeds."""
    allowed = {"downstream", *([variant.section] if variant.section else [])}
    for key in variant.set:
        root, _, rest = key.partition(".")
        if not rest or root not in allowed:
            raise ValueError(
                f"study.variants.{name}.set: key {key!r} is not a setting of arm {variant.arm}'s "
                f"fine-tuning: use {' or '.join(f'{a}.<field>' for a in sorted(allowed))}"
            )
        if root == "downstream" and rest.split(".")[0] in FIXED:
            raise ValueError(
                f"study.variants.{name}.set: key {key!r} is the study's (budgets, lr grid `lrs`, seeds), "
                "not a variant's"
            )


def variant_config(data: dict[str, Any], name: str, variant: Variant) -> PipelineConfig:
    """The study's pipeline settings (`data`, as JSON, its `study` section left out) with variant `name`'s
    overrides applied and validated; an error names the variant and what is wrong."""
    base = {k: v for k, v in data.items() if k != "study"}
    try:
        return PipelineConfig.model_validate(apply_overrides(base, overrides(variant), PipelineConfig))
    except ValidationError as e:
        what = "; ".join(f"{'.'.join(map(str, x['loc']))}: {x['msg']}" for x in e.errors())
        raise ValueError(f"study.variants.{name}.set: {what}") from None
    except ValueError as e:  # an unknown key (it names the key and what is known there)
        raise ValueError(f"study.variants.{name}.set: {e}") from None


def check_variants(variants: dict[str, Variant], data: dict[str, Any]) -> None:
    """Each variant's name, keys and overridden config, checked when the study is loaded."""
    for name, variant in variants.items():
        if not NAME.fullmatch(name):
            raise ValueError(
                f"study.variants: name {name!r} must be lower-case letters, digits and _ (it names steps "
                "and the analysis's inputs)"
            )
        _check_keys(name, variant)
        variant_config(data, name, variant)
