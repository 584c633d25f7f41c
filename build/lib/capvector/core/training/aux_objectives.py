"""Auxiliary training objectives, used only during training (heads are dropped afterwards).

Each objective is an ``nn.Module`` holding its own head parameters, separate from the policy, so
θ_ao (SFT + aux) and θ_ft (plain SFT) have identical keys and a capability vector is well defined.
An objective declares the policy features it reads (``required_features``: names from the policy's
``feature_specs()``, so any policy that exposes them works), the dataset fields it needs
(``required_fields``) and, if it looks ahead in time, its ``horizon``; the policy's batcher then
supplies ``batch["privileged_future"]`` for that horizon.

- ``spatial`` — the Spatial Forcing analogue. Hidden states of an intermediate layer at the vision
  tokens (state tokens in ``state`` mode; feature ``obs_tokens``) go through LayerNorm -> Linear ->
  GELU -> Linear and are aligned by cosine similarity with fixed 3D scene features: the privileged
  object/goal/hand xyz, standardized with dataset statistics and embedded by a fixed random Fourier map
  ``[sin(Wx), cos(Wx)]`` (W ~ N(0, scale²), seeded, never trained — a frozen "3D encoder" in the role
  VGGT plays in the paper, so the target cannot collapse). ``pooling="mean"`` aligns the mean token;
  ``pooling="token"`` aligns every token with the scene feature plus a fixed sinusoidal embedding of
  its position (the paper's f + E). Loss = 1 − mean cosine.
- ``spatial_depth`` — a closer Spatial Forcing analogue for ``pixels`` mode: each vision token is
  aligned with a 3D feature of *its own* image patch rather than with one scene vector. The target of
  a token is the world xyz its patch sees (dataset field ``patch_xyz``: back-projected from the
  rendered depth through the camera's pinhole model, median over the patch; recorded by demos with
  ``DemoConfig(patch_xyz=True)``, see depth_targets.py), standardized per coordinate with dataset
  statistics and embedded by a fixed random Fourier map (seeded, never trained), plus the token's
  0.1-scaled sinusoidal position as in ``spatial``'s token mode. Head as in ``spatial``; loss = 1 − mean
  cosine over the tokens whose patch sees geometry (a patch of sky only has NaN xyz and is skipped).
  The dataset's patch grid must be the policy's token grid.
- ``dynamics`` — an MLP on the mean-pooled final backbone state (feature ``tokens``) predicts the
  standardized privileged state ``horizon`` steps ahead in the same episode (clamped at the episode's
  end); loss = MSE.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Callable, Mapping
from typing import Literal

import torch
import torch.nn.functional as F
from pydantic import BaseModel, ConfigDict, Field
from torch import nn

from capvector.core.policies.base import FeatureSpec

_REGISTRY: dict[str, type[AuxObjective]] = {}


def register_objective(name: str) -> Callable[[type[AuxObjective]], type[AuxObjective]]:
    def deco(cls: type[AuxObjective]) -> type[AuxObjective]:
        if name in _REGISTRY:
            raise ValueError(f"auxiliary objective {name!r} is already registered")
        cls.name = name
        _REGISTRY[name] = cls
        return cls

    return deco


def get_objective(name: str) -> type[AuxObjective]:
    if name not in _REGISTRY:
        raise ValueError(f"unknown auxiliary objective {name!r}; known: {sorted(_REGISTRY)}")
    return _REGISTRY[name]


def known_objectives() -> list[str]:
    return sorted(_REGISTRY)


def build_objective(
    name: str, features: Mapping[str, FeatureSpec], params: Mapping | None = None, seed: int | None = None
) -> AuxObjective:
    """Instantiate a registered objective for a policy exposing `features` (`policy.feature_specs()`).

    `seed`: its heads are initialised from a generator of their own seeded with it, and torch's global
    RNG is left as it was (so θ_ao's run draws what θ_ft's does); None: from the global RNG.
    """
    cls = get_objective(name)
    missing = [f for f in cls.feature_names if f not in features]
    if missing:
        raise ValueError(
            f"auxiliary objective {name!r} needs policy feature(s) {missing}; this policy exposes "
            f"{sorted(features)}"
        )
    validated = cls.Params.model_validate(dict(params or {}))
    if seed is None:
        return cls(features, validated)
    # The heads are built on the CPU with torch's default initialisers, which draw from the global CPU
    # generator: it is forked (saved, seeded, restored), the heads' own generator for the moment.
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return cls(features, validated)


class AuxObjective(nn.Module, abc.ABC):
    name = ""
    feature_names: tuple[str, ...] = ()  # the policy features `forward` reads

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")

    def __init__(self, features: Mapping[str, FeatureSpec], params: BaseModel):
        super().__init__()
        self.params = params
        self.register_buffer("privileged_mean", torch.zeros(9))
        self.register_buffer("privileged_std", torch.ones(9))

    @property
    def horizon(self) -> int | None:
        """Steps ahead the objective needs privileged state for (None: only the current step)."""
        return None

    def required_fields(self) -> list[str]:
        """Dataset fields this objective needs (checked before training starts)."""
        return ["privileged"]

    def fit(self, tensors: Mapping[str, torch.Tensor]) -> None:
        """Take standardization statistics of the privileged state from the training data."""
        priv = tensors["privileged"].double()
        self.privileged_mean.copy_(priv.mean(0).float())
        self.privileged_std.copy_(priv.std(0, unbiased=False).clamp_min(1e-2).float())

    def standardize(self, privileged: torch.Tensor) -> torch.Tensor:
        return (privileged - self.privileged_mean) / self.privileged_std

    @abc.abstractmethod
    def forward(
        self, features: Mapping[str, list[torch.Tensor]], batch: Mapping[str, torch.Tensor]
    ) -> torch.Tensor:
        """The (unweighted) auxiliary loss for one batch, from the policy's per-layer features."""


def _mlp(d_in: int, hidden: int, d_out: int) -> nn.Sequential:
    return nn.Sequential(nn.LayerNorm(d_in), nn.Linear(d_in, hidden), nn.GELU(), nn.Linear(hidden, d_out))


def _resolve_layer(layer: int, n_layers: int, field: str) -> int:
    idx = layer if layer >= 0 else n_layers + layer
    if not 0 <= idx < n_layers:
        raise ValueError(f"{field}={layer} is out of range for a policy with n_layers={n_layers}")
    return idx


def _token_alignment(
    objective: AuxObjective, features: Mapping[str, FeatureSpec], params: BaseModel, name: str, point_dim: int
) -> FeatureSpec:
    """What both Spatial Forcing analogues share: the hidden layer they read (3/4 depth by default),
    the head on its vision tokens and the frozen, seeded Fourier map of `point_dim`-d points."""
    if params.feature_dim % 2:
        raise ValueError(f"{name} feature_dim must be even, got {params.feature_dim}")
    spec = features["obs_tokens"]
    default = max(0, math.ceil(0.75 * spec.n_layers) - 1)
    layer = default if params.layer is None else params.layer
    objective.layer = _resolve_layer(layer, spec.n_layers, f"{name} layer")
    objective.head = _mlp(spec.dim, params.hidden_dim, params.feature_dim)
    gen = torch.Generator().manual_seed(params.seed)
    fourier = torch.randn(point_dim, params.feature_dim // 2, generator=gen) * params.fourier_scale
    objective.register_buffer("fourier", fourier)
    return spec


@register_objective("spatial")
class SpatialObjective(AuxObjective):
    feature_names = ("obs_tokens",)

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        layer: int | None = Field(
            None, description="hidden layer index (negative from the end); default 3/4 depth"
        )
        pooling: Literal["mean", "token"] = "token"
        hidden_dim: int = Field(256, gt=0)
        feature_dim: int = Field(128, gt=0, description="random Fourier feature size (even)")
        fourier_scale: float = Field(1.0, gt=0)
        seed: int = 0

    def __init__(self, features: Mapping[str, FeatureSpec], params: Params):
        super().__init__(features, params)
        spec = _token_alignment(self, features, params, "spatial", point_dim=9)
        self.register_buffer("token_pos", _sinusoid(spec.n_tokens, params.feature_dim))

    def target(self, privileged: torch.Tensor) -> torch.Tensor:
        z = self.standardize(privileged) @ self.fourier
        return torch.cat([z.sin(), z.cos()], dim=-1)

    def forward(self, features: Mapping, batch: Mapping[str, torch.Tensor]) -> torch.Tensor:
        tokens = features["obs_tokens"][self.layer]
        target = self.target(batch["privileged"])
        if self.params.pooling == "mean":
            pred = self.head(tokens.mean(1))
        else:
            pred = self.head(tokens)
            target = target[:, None, :] + self.token_pos
        return 1.0 - F.cosine_similarity(pred, target, dim=-1).mean()


@register_objective("spatial_depth")
class SpatialDepthObjective(AuxObjective):
    feature_names = ("obs_tokens",)

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        layer: int | None = Field(
            None, description="hidden layer index (negative from the end); default 3/4 depth"
        )
        hidden_dim: int = Field(256, gt=0)
        feature_dim: int = Field(128, gt=0, description="random Fourier feature size (even)")
        fourier_scale: float = Field(1.0, gt=0)
        position_embedding: bool = Field(True, description="add each token's 0.1-scaled sinusoid (SF's E)")
        seed: int = 0

    def __init__(self, features: Mapping[str, FeatureSpec], params: Params):
        super().__init__(features, params)
        spec = _token_alignment(self, features, params, "spatial_depth", point_dim=3)
        self.n_tokens = spec.n_tokens
        position = _sinusoid(spec.n_tokens, params.feature_dim)
        self.register_buffer(
            "token_pos", position if params.position_embedding else torch.zeros_like(position)
        )
        self.register_buffer("xyz_mean", torch.zeros(3))
        self.register_buffer("xyz_std", torch.ones(3))

    def required_fields(self) -> list[str]:
        return ["patch_xyz"]

    def fit(self, tensors: Mapping[str, torch.Tensor]) -> None:
        """Check the patch grid against the policy's tokens; per-coordinate statistics of the points."""
        patches = tensors["patch_xyz"]
        if patches.ndim != 3 or patches.shape[2] != 3 or patches.shape[1] != self.n_tokens:
            raise ValueError(
                f"auxiliary objective 'spatial_depth' needs patch_xyz with one point per vision token, "
                f"(N, {self.n_tokens}, 3); the dataset has {tuple(patches.shape)}: collect the demos with "
                f"patch_grid = the policy's token grid, image_size / 2**len(stem_channels) "
                f"({math.isqrt(self.n_tokens)} here)"
            )
        points = patches.reshape(-1, 3).double()
        points = points[torch.isfinite(points).all(1)]
        if not len(points):
            raise ValueError("auxiliary objective 'spatial_depth': no patch of the dataset sees any geometry")
        self.xyz_mean.copy_(points.mean(0).float())
        self.xyz_std.copy_(points.std(0, unbiased=False).clamp_min(1e-2).float())

    def target(self, patch_xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, T, feature_dim) targets and the (B, T) mask of patches that see geometry."""
        valid = torch.isfinite(patch_xyz).all(-1)
        standard = (patch_xyz - self.xyz_mean) / self.xyz_std
        z = torch.where(valid[..., None], standard, torch.zeros_like(standard)) @ self.fourier
        return torch.cat([z.sin(), z.cos()], dim=-1) + self.token_pos, valid

    def forward(self, features: Mapping, batch: Mapping[str, torch.Tensor]) -> torch.Tensor:
        tokens = features["obs_tokens"][self.layer]
        patch_xyz = batch["patch_xyz"]
        if patch_xyz.shape[:2] != tokens.shape[:2]:
            raise ValueError(
                f"patch_xyz {tuple(patch_xyz.shape)} does not match the vision tokens {tuple(tokens.shape)}"
            )
        target, valid = self.target(patch_xyz)
        cosine = F.cosine_similarity(self.head(tokens), target, dim=-1)
        mask = valid.to(cosine.dtype)
        return 1.0 - (cosine * mask).sum() / mask.sum().clamp_min(1.0)


def _sinusoid(n: int, dim: int) -> torch.Tensor:
    pos = torch.arange(n, dtype=torch.float32)[:, None]
    freq = torch.exp(torch.arange(0, dim, 2, dtype=torch.float32) * (-math.log(1e4) / dim))
    table = torch.zeros(n, dim)
    table[:, 0::2] = torch.sin(pos * freq)
    table[:, 1::2] = torch.cos(pos * freq)
    return table * 0.1  # SF scales its positional term by 0.1 so the scene feature dominates


@register_objective("dynamics")
class DynamicsObjective(AuxObjective):
    feature_names = ("tokens",)

    class Params(BaseModel):
        model_config = ConfigDict(extra="forbid")
        horizon: int = Field(5, gt=0, description="steps ahead, within the episode")
        layer: int = Field(-1, description="hidden layer index (negative from the end)")
        hidden_dim: int = Field(256, gt=0)

    def __init__(self, features: Mapping[str, FeatureSpec], params: Params):
        super().__init__(features, params)
        spec = features["tokens"]
        self.layer = _resolve_layer(params.layer, spec.n_layers, "dynamics layer")
        self.head = _mlp(spec.dim, params.hidden_dim, 9)

    @property
    def horizon(self) -> int:
        return self.params.horizon

    def forward(self, features: Mapping, batch: Mapping[str, torch.Tensor]) -> torch.Tensor:
        pooled = features["tokens"][self.layer].mean(1)
        return F.mse_loss(self.head(pooled), self.standardize(batch["privileged_future"]))
