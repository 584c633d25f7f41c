"""Fixed, seeded maps of the state a policy sees: a testbed where an auxiliary target carries what the
input hides.

Meta-World's 39-number state holds the object, goal and hand positions in clear, so an auxiliary
objective that predicts them (``spatial``, ``dynamics``) can only regularize: there is nothing for it to
teach. ``random_features`` passes the standardized state through a frozen random map, as a camera
does to a scene: ``sin(z·W + b)`` with ``W ~ N(0, frequency²)`` entry-wise (``features`` of them), plus
``distractors`` dimensions that encode the ``aliased`` positions (the goal; optionally the object, now
and in the previous frame) at a high frequency. An aliased position is left out of the random
features, so the policy sees it only through those distractors: hard to decode from the action loss
alone, and exactly what a privileged xyz target teaches. Proprioception stays in clear in its own
token.
The map is part of the policy (its config holds the seed; its tensors are rebuilt from it, never
stored or trained), so demonstrations, training and evaluation cannot disagree about it, and
capability vectors see the same parameter keys as without it.
"""

from __future__ import annotations

import math
from typing import Literal

import torch
from pydantic import BaseModel, ConfigDict, Field, model_validator
from torch import nn

POSITIONS: dict[str, tuple[slice, ...]] = {
    "goal": (slice(36, 39),),
    "object": (slice(4, 7), slice(22, 25)),  # the first object's xyz, now and in the previous frame
}
"""Where each position that can be aliased sits in Meta-World's 39-number state."""


class ObsTransformConfig(BaseModel):
    """How the policy's state input is transformed before its state tokens.

    Args:
        kind: ``identity`` (the state as it is) or ``random_features`` (see the module docstring).
        seed: seed of the random map; a different seed is a different observation space.
        features: number of random sine features of the standardized state.
        frequency: standard deviation of the map's entries; the argument of each sine has a standard
            deviation of about ``frequency·√(state dims)`` radians, so larger values hide more.
        distractors: extra dimensions that encode the aliased positions at ``distractor_frequency``.
        distractor_frequency: standard deviation of the distractors' entries (high: aliased).
        aliased: positions (``goal``, ``object``) the distractors encode; with ``hide_aliased`` they
            are left out of the random features, so the distractors are the only way to see them.
        hide_aliased: leave the aliased positions out of the random features.
        tokens: the transformed vector is split into this many equal state tokens (the ``spatial``
            objective aligns each of them, as it aligns vision tokens in pixels mode).
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)
    kind: Literal["identity", "random_features"] = "identity"
    seed: int = 0
    features: int = Field(128, gt=0)
    frequency: float = Field(1.0, gt=0)
    distractors: int = Field(32, ge=0)
    distractor_frequency: float = Field(20.0, gt=0)
    aliased: list[Literal["goal", "object"]] = Field(default_factory=lambda: ["goal"])
    hide_aliased: bool = False
    tokens: int = Field(5, gt=0)

    @model_validator(mode="after")
    def _tokens_divide(self) -> ObsTransformConfig:
        if self.kind != "identity" and self.out_dim % self.tokens:
            raise ValueError(
                f"obs_transform: features + distractors ({self.out_dim}) must be divisible by tokens "
                f"({self.tokens}), one equal slice per state token"
            )
        return self

    @property
    def active(self) -> bool:
        return self.kind != "identity"

    @property
    def out_dim(self) -> int:
        return self.features + self.distractors

    def aliased_dims(self) -> list[int]:
        """State dimensions the distractors encode (and, hidden, the random features leave out)."""
        return sorted(
            {i for name in self.aliased for part in POSITIONS[name] for i in range(part.start, part.stop)}
        )


class ObsTransform(nn.Module):
    """The map of `ObsTransformConfig` on a (B, state_dim) standardized state; identity when inactive.

    Its tensors are non-persistent buffers rebuilt from the seed (on the CPU generator, so the same on
    every machine): a checkpoint holds only the config."""

    def __init__(self, config: ObsTransformConfig, state_dim: int):
        super().__init__()
        self.config = config
        if not config.active:
            return
        aliased = config.aliased_dims()
        if aliased and max(aliased) >= state_dim:
            raise ValueError(
                f"obs_transform aliases state dims {aliased} ({config.aliased}); the state has {state_dim}"
            )
        gen = torch.Generator().manual_seed(config.seed)
        weight = torch.randn(state_dim, config.features, generator=gen) * config.frequency
        phase = torch.rand(config.features, generator=gen) * 2 * math.pi
        aliased_weight = torch.randn(len(aliased), config.distractors, generator=gen)
        aliased_phase = torch.rand(config.distractors, generator=gen) * 2 * math.pi
        if config.hide_aliased:
            weight[aliased] = 0.0  # the random features do not see the aliased positions at all
        self.register_buffer("weight", weight, persistent=False)
        self.register_buffer("phase", phase, persistent=False)
        self.register_buffer("aliased", torch.tensor(aliased, dtype=torch.long), persistent=False)
        self.register_buffer("aliased_weight", aliased_weight * config.distractor_frequency, persistent=False)
        self.register_buffer("aliased_phase", aliased_phase, persistent=False)

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        if not self.config.active:
            return state
        features = torch.sin(state @ self.weight + self.phase)
        if not self.config.distractors:
            return features
        distractors = torch.sin(state[:, self.aliased] @ self.aliased_weight + self.aliased_phase)
        return torch.cat([features, distractors], dim=1)
