"""The token backbone both built-in policies share: language + (vision | state) + proprio tokens.

Prefix token layout: ``[language (max_instruction_tokens) | obs tokens | proprio (1)]``; a policy
may append its own tokens (the L1 chunk policy's action queries) to the same sequence.

Obs tokens are either a conv stem's grid over the image (``pixels``) or, in ``state`` mode, the
39-number Meta-World observation split into five semantic groups, one token each: hand+gripper (0:4),
object 1 pose (4:11), object 2 pose (11:18), the previous frame of those (18:36) and the goal (36:39).
Grouping gives the ``spatial`` objective several tokens to align, as vision tokens do in pixels mode.

The transformer is hand-written pre-norm with separate ``nn.Linear`` q/k/v/o projections, so adapters
can target them by name. Parameter names are part of the interface (capability vectors are
per-tensor)::

    language.embed.weight                    state.proj.<group>.{weight,bias}   (state mode)
    vision.stem.<2i>.{weight,bias}           vision.proj.{weight,bias}          (pixels mode)
    proprio.proj.{weight,bias}               embeddings.{position,token_type.weight}
    backbone.layers.<i>.{norm1,norm2}.*      backbone.layers.<i>.attn.{q,k,v,o}_proj.*
    backbone.layers.<i>.mlp.{fc1,fc2}.*      backbone.norm.*
    normalizer.{state,proprio,action}_{mean,std}, normalizer.fitted
"""

from __future__ import annotations

import abc
from collections.abc import Collection, Mapping
from typing import Any, Literal

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import Field, field_validator, model_validator
from torch import nn

from capvector.core.policies import tokenizer
from capvector.core.policies.base import Batch, Batcher, FeatureSpec, Policy, PolicyConfig
from capvector.core.simulation.obs_transforms import ObsTransform, ObsTransformConfig
from capvector.core.training.batching import DemoBatcher

STATE_GROUPS: dict[str, tuple[int, int]] = {
    "hand": (0, 4),
    "obj1": (4, 11),
    "obj2": (11, 18),
    "prev": (18, 36),
    "goal": (36, 39),
}


class TokenBackboneConfig(PolicyConfig):
    """Architecture and input settings shared by the token-backbone policies."""

    d_model: int = Field(
        128, gt=0, description="transformer width (every token's size); divisible by n_heads; cost ~ d_model²"
    )
    n_layers: int = Field(4, gt=0, description="transformer blocks (depth)")
    n_heads: int = Field(4, gt=0, description="attention heads per block (d_model / n_heads per head)")
    ffn_mult: int = Field(4, gt=0, description="MLP hidden size as a multiple of d_model")
    dropout: float = Field(
        0.0, ge=0.0, lt=1.0, description="dropout probability in attention and MLPs, training only (0-1)"
    )
    chunk_size: int = Field(8, gt=0, description="K: actions predicted per call")
    stem_channels: list[int] = Field(
        default_factory=lambda: [32, 64, 64, 128],
        description="output channels of the pixels conv stem, one stride-2 conv each: the token grid is "
        "image_size / 2**len(stem_channels) per side",
    )
    state_tokens: Literal["grouped", "single"] = Field(
        "grouped",
        description="state mode: `grouped` (five tokens: hand, object 1, object 2, previous frame, goal; "
        "needs state_dim 39) or `single` (one token for the whole state)",
    )
    vocab_size: int = Field(
        512, ge=2, description="hashed instruction-word ids (id 0 is padding); smaller: more collisions"
    )
    max_instruction_tokens: int = Field(
        12, gt=0, description="instruction words kept (longer ones are cut); language tokens per sequence"
    )
    state_dim: int = Field(39, gt=0, description="size of the state vector (Meta-World's is 39)")
    proprio_dim: int = Field(4, gt=0, description="size of the proprioception vector (hand xyz, gripper)")
    action_dim: int = Field(4, gt=0, description="size of one action (Meta-World: Δxyz and gripper)")
    obs_transform: ObsTransformConfig = Field(
        default_factory=ObsTransformConfig,
        description="fixed map of the standardized state before the state tokens "
        "(capvector.core.simulation.obs_transforms)",
    )

    @field_validator("stem_channels")
    @classmethod
    def _channels_positive(cls, value: list[int]) -> list[int]:
        if not value or any(c <= 0 for c in value):
            raise ValueError(f"stem_channels must be a non-empty list of positive ints, got {value}")
        return value

    @model_validator(mode="after")
    def _consistent(self) -> TokenBackboneConfig:
        if self.d_model % self.n_heads:
            raise ValueError(f"d_model ({self.d_model}) must be divisible by n_heads ({self.n_heads})")
        if self.obs_mode == "pixels":
            factor = 2 ** len(self.stem_channels)
            if self.image_size % factor:
                raise ValueError(
                    f"image_size ({self.image_size}) must be divisible by 2**len(stem_channels) = {factor} "
                    "(each stem conv halves the image)"
                )
        if self.obs_transform.active and self.obs_mode != "state":
            raise ValueError(
                f"obs_transform {self.obs_transform.kind!r} maps the state: obs_mode must be 'state'"
            )
        if self.state_tokens == "grouped" and self.state_dim != 39 and not self.obs_transform.active:
            raise ValueError(
                f"state_dim ({self.state_dim}) must be 39 with state_tokens='grouped' (Meta-World layout); "
                "use state_tokens='single' for other state sizes"
            )
        return self

    @property
    def grid_size(self) -> int:
        return self.image_size // 2 ** len(self.stem_channels)

    @property
    def n_obs_tokens(self) -> int:
        if self.obs_mode == "pixels":
            return self.grid_size**2
        if self.obs_transform.active:
            return self.obs_transform.tokens
        return len(STATE_GROUPS) if self.state_tokens == "grouped" else 1

    @property
    def n_prefix_tokens(self) -> int:
        return self.max_instruction_tokens + self.n_obs_tokens + 1

    @property
    def obs_key(self) -> str:
        return "image" if self.obs_mode == "pixels" else "state"

    def prefix_slices(self) -> dict[str, slice]:
        lang = self.max_instruction_tokens
        obs = lang + self.n_obs_tokens
        return {"language": slice(0, lang), "obs": slice(lang, obs), "proprio": slice(obs, obs + 1)}


class Normalizer(nn.Module):
    """Input/output statistics as buffers, so a saved policy acts in env units without its dataset."""

    def __init__(self, config: TokenBackboneConfig):
        super().__init__()
        for key, dim in (
            ("state", config.state_dim),
            ("proprio", config.proprio_dim),
            ("action", config.action_dim),
        ):
            self.register_buffer(f"{key}_mean", torch.zeros(dim))
            self.register_buffer(f"{key}_std", torch.ones(dim))
        self.register_buffer("fitted", torch.zeros(()))

    def set_stats(self, stats: Mapping[str, tuple[torch.Tensor, torch.Tensor]]) -> None:
        """stats: key -> (mean, std) for state, proprio and action."""
        for key in ("state", "proprio", "action"):
            mean, std = stats[key]
            getattr(self, f"{key}_mean").copy_(torch.as_tensor(mean, dtype=torch.float32))
            getattr(self, f"{key}_std").copy_(torch.as_tensor(std, dtype=torch.float32))
        self.fitted.fill_(1.0)

    def fit(self, tensors: Mapping[str, torch.Tensor]) -> None:
        stats = {}
        for key in ("state", "proprio", "action"):
            x = tensors[key].double()
            # Constant dimensions (e.g. an absent second object) get std 1e-2, not ~0: a shift at test
            # time must not blow up.
            stats[key] = (x.mean(0).float(), x.std(0, unbiased=False).clamp_min(1e-2).float())
        self.set_stats(stats)

    def normalize(self, key: str, x: torch.Tensor) -> torch.Tensor:
        return (x - getattr(self, f"{key}_mean")) / getattr(self, f"{key}_std")

    def denormalize(self, key: str, x: torch.Tensor) -> torch.Tensor:
        return x * getattr(self, f"{key}_std") + getattr(self, f"{key}_mean")


def dropout(x: torch.Tensor, p: float, training: bool, generator: torch.Generator | None) -> torch.Tensor:
    """Inverted dropout whose mask is drawn from `generator` (None: torch's global RNG, `F.dropout`)."""
    if not training or p == 0.0:
        return x
    if generator is None:
        return F.dropout(x, p, True)
    keep = torch.empty_like(x).bernoulli_(1.0 - p, generator=generator)
    return x * keep / (1.0 - p)


def split_heads(y: torch.Tensor, n_heads: int) -> torch.Tensor:
    b, t, d = y.shape
    return y.view(b, t, n_heads, d // n_heads).transpose(1, 2)


def merge_heads(y: torch.Tensor) -> torch.Tensor:
    b, h, t, dh = y.shape
    return y.transpose(1, 2).reshape(b, t, h * dh)


class Attention(nn.Module):
    """Multi-head attention with named q/k/v/o projections; `kv_prefix` is attended to as well."""

    def __init__(self, d_model: int, n_heads: int, dropout: float):
        super().__init__()
        self.n_heads = n_heads
        self.dropout = dropout
        self.q_proj = nn.Linear(d_model, d_model)
        self.k_proj = nn.Linear(d_model, d_model)
        self.v_proj = nn.Linear(d_model, d_model)
        self.o_proj = nn.Linear(d_model, d_model)

    def keys_values(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return split_heads(self.k_proj(x), self.n_heads), split_heads(self.v_proj(x), self.n_heads)

    def forward(
        self,
        x: torch.Tensor,
        key_mask: torch.Tensor,
        kv_prefix: tuple[torch.Tensor, torch.Tensor] | None = None,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        k, v = self.keys_values(x)
        if kv_prefix is not None:
            k, v = torch.cat([kv_prefix[0], k], dim=2), torch.cat([kv_prefix[1], v], dim=2)
        q = split_heads(self.q_proj(x), self.n_heads)
        mask = key_mask[:, None, None, :]
        if self.training and self.dropout > 0.0 and generator is not None:
            # SDPA draws its dropout mask from the global RNG: written out to draw from `generator`
            scores = (q @ k.transpose(-2, -1)) * q.shape[-1] ** -0.5
            weights = scores.masked_fill(~mask, float("-inf")).softmax(-1)
            out = dropout(weights, self.dropout, True, generator) @ v
        else:
            p = self.dropout if self.training else 0.0
            out = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=p)
        return self.o_proj(merge_heads(out))


class MLP(nn.Module):
    def __init__(self, d_model: int, hidden: int, dropout: float):
        super().__init__()
        self.fc1 = nn.Linear(d_model, hidden)
        self.fc2 = nn.Linear(hidden, d_model)
        self.drop = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        return dropout(self.fc2(F.gelu(self.fc1(x))), self.drop.p, self.training, generator)


class Block(nn.Module):
    def __init__(self, config: TokenBackboneConfig):
        super().__init__()
        d = config.d_model
        self.norm1 = nn.LayerNorm(d)
        self.attn = Attention(d, config.n_heads, config.dropout)
        self.norm2 = nn.LayerNorm(d)
        self.mlp = MLP(d, d * config.ffn_mult, config.dropout)
        self.drop = nn.Dropout(config.dropout)

    def forward(self, x, key_mask, kv_prefix=None, generator: torch.Generator | None = None) -> torch.Tensor:
        """`generator`: where the dropout masks are drawn from (None: torch's global RNG)."""
        attended = self.attn(self.norm1(x), key_mask, kv_prefix, generator)
        x = x + dropout(attended, self.drop.p, self.training, generator)
        return x + self.mlp(self.norm2(x), generator)


class Backbone(nn.Module):
    def __init__(self, config: TokenBackboneConfig):
        super().__init__()
        self.layers = nn.ModuleList(Block(config) for _ in range(config.n_layers))
        self.norm = nn.LayerNorm(config.d_model)


class LanguageEncoder(nn.Module):
    def __init__(self, config: TokenBackboneConfig):
        super().__init__()
        self.embed = nn.Embedding(config.vocab_size, config.d_model, padding_idx=tokenizer.PAD_ID)
        nn.init.normal_(self.embed.weight, std=0.02)
        with torch.no_grad():
            self.embed.weight[tokenizer.PAD_ID].zero_()


class VisionEncoder(nn.Module):
    """Strided 3x3 convs (each halves the image) -> grid of tokens -> linear to d_model."""

    def __init__(self, config: TokenBackboneConfig):
        super().__init__()
        layers: list[nn.Module] = []
        c_in = 3
        for c in config.stem_channels:
            layers += [nn.Conv2d(c_in, c, kernel_size=3, stride=2, padding=1), nn.GELU()]
            c_in = c
        self.stem = nn.Sequential(*layers)
        self.proj = nn.Linear(c_in, config.d_model)
        self.image_size = config.image_size

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        if image.dtype != torch.uint8 or image.shape[1:] != (self.image_size, self.image_size, 3):
            raise ValueError(
                f"image must be uint8 (B, {self.image_size}, {self.image_size}, 3), "
                f"got {image.dtype} {tuple(image.shape)}"
            )
        x = image.permute(0, 3, 1, 2).float() / 255.0 - 0.5
        grid = self.stem(x)
        return self.proj(grid.flatten(2).transpose(1, 2))


def _state_groups(config: TokenBackboneConfig) -> dict[str, tuple[int, int]]:
    """Token name -> slice of the (transformed) state: the semantic groups, one token, or equal
    slices of a random-feature map (its features are exchangeable, so any split is as good)."""
    transform = config.obs_transform
    if transform.active:
        width = transform.out_dim // transform.tokens
        return {f"features{i}": (i * width, (i + 1) * width) for i in range(transform.tokens)}
    return dict(STATE_GROUPS) if config.state_tokens == "grouped" else {"all": (0, config.state_dim)}


class StateEncoder(nn.Module):
    def __init__(self, config: TokenBackboneConfig):
        super().__init__()
        self.transform = ObsTransform(config.obs_transform, config.state_dim)
        self.groups = _state_groups(config)
        self.proj = nn.ModuleDict(
            {name: nn.Linear(b - a, config.d_model) for name, (a, b) in self.groups.items()}
        )

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        state = self.transform(state)
        return torch.stack([self.proj[name](state[:, a:b]) for name, (a, b) in self.groups.items()], dim=1)


class ActionHead(nn.Module):
    """Final token states -> one action (or velocity) per action token: `action_head.proj`."""

    def __init__(self, config: TokenBackboneConfig):
        super().__init__()
        self.proj = nn.Linear(config.d_model, config.action_dim)


class Embeddings(nn.Module):
    """Learned positions and token types for the prefix plus `extra` policy tokens (action queries)."""

    def __init__(self, config: TokenBackboneConfig, extra: int = 0):
        super().__init__()
        n_types = 3 + (1 if extra else 0)
        self.position = nn.Parameter(torch.randn(config.n_prefix_tokens + extra, config.d_model) * 0.02)
        if extra:
            self.action_queries = nn.Parameter(torch.randn(extra, config.d_model) * 0.02)
        self.token_type = nn.Embedding(n_types, config.d_model)
        nn.init.normal_(self.token_type.weight, std=0.02)


class TokenPolicy(Policy):
    """Shared inputs, normalizer, batches and inference plumbing; subclasses add their action head."""

    config: TokenBackboneConfig

    def __init__(self, config: TokenBackboneConfig, extra_tokens: int = 0):
        super().__init__(config)
        self.language = LanguageEncoder(config)
        if config.obs_mode == "pixels":
            self.vision = VisionEncoder(config)
        else:
            self.state = StateEncoder(config)
        self.proprio = nn.Module()
        self.proprio.proj = nn.Linear(config.proprio_dim, config.d_model)
        self.embeddings = Embeddings(config, extra_tokens)
        self.backbone = Backbone(config)
        self.normalizer = Normalizer(config)
        spans = [s.stop - s.start for s in config.prefix_slices().values()] + (
            [extra_tokens] if extra_tokens else []
        )
        type_ids = torch.cat([torch.full((n,), i) for i, n in enumerate(spans)])
        self.register_buffer("_type_ids", type_ids, persistent=False)
        self._instruction_tokens: dict[str, torch.Tensor] = {}

    # ------------------------------------------------------------------ data
    def required_fields(self) -> list[str]:
        return [self.config.obs_key, "proprio", "action", "episode", "step", "task"]

    def check_dataset(self, dataset: Any) -> None:
        super().check_dataset(dataset)
        if self.config.obs_mode == "pixels":
            size = self.config.image_size
            if tuple(dataset.tensors["image"].shape[1:]) != (size, size, 3):
                raise ValueError(
                    f"dataset images are {tuple(dataset.tensors['image'].shape[1:])}, "
                    f"the policy expects ({size}, {size}, 3)"
                )

    @property
    def normalizer_fitted(self) -> bool:
        return bool(self.normalizer.fitted)

    def fit_normalizer(self, tensors: Mapping[str, torch.Tensor]) -> None:
        self.normalizer.fit(tensors)

    def make_batcher(
        self, dataset: Any, device: torch.device, fields: Collection[str] = (), horizon: int | None = None
    ) -> tuple[int, Batcher]:
        cfg = self.config
        batcher = DemoBatcher(
            dataset,
            [cfg.obs_key, "proprio"],
            cfg.chunk_size,
            cfg.vocab_size,
            cfg.max_instruction_tokens,
            device,
            fields,
            horizon,
        )
        return batcher.n, batcher

    # ------------------------------------------------------------------ shared forward pieces
    def embed_inputs(self, batch: Batch) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, prefix, d) input embeddings without positions, and the (B, prefix) key mask."""
        cfg = self.config
        tokens = batch["tokens"]
        if tokens.shape[1] != cfg.max_instruction_tokens:
            raise ValueError(
                f"tokens must have {cfg.max_instruction_tokens} columns, got {tuple(tokens.shape)}"
            )
        lang = self.language.embed(tokens)
        if cfg.obs_mode == "pixels":
            obs = self.vision(batch["image"])
        else:
            obs = self.state(self.normalizer.normalize("state", batch["state"]))
        proprio = self.proprio.proj(self.normalizer.normalize("proprio", batch["proprio"]))[:, None]
        x = torch.cat([lang, obs, proprio], dim=1)
        mask = torch.ones(x.shape[:2], dtype=torch.bool, device=x.device)
        mask[:, : tokens.shape[1]] = tokens != tokenizer.PAD_ID
        return x, mask

    def prefix_features(
        self, hidden: list[torch.Tensor], names: Collection[str]
    ) -> dict[str, list[torch.Tensor]]:
        obs = self.config.prefix_slices()["obs"]
        out = {}
        if "obs_tokens" in names:
            out["obs_tokens"] = [h[:, obs] for h in hidden]
        if "tokens" in names:
            out["tokens"] = hidden
        unknown = sorted(set(names) - set(out))
        if unknown:
            raise ValueError(
                f"{self.type_name} policy has no feature(s) {unknown}; it has {sorted(self.feature_specs())}"
            )
        return out

    # ------------------------------------------------------------------ inference
    def set_instructions(self, instructions: Mapping[str, str]) -> None:
        """Tokenize task -> instruction once; used by predict_action_chunk."""
        cfg = self.config
        self._instruction_tokens = {
            task: torch.tensor(tokenizer.encode(text, cfg.vocab_size, cfg.max_instruction_tokens))
            for task, text in instructions.items()
        }

    def tokens_for(self, task_names: list[str]) -> torch.Tensor:
        if not self._instruction_tokens:
            from capvector.core.simulation.metaworld_tasks import (
                INSTRUCTIONS,  # lazy: keeps policies usable alone
            )

            self.set_instructions(INSTRUCTIONS)
        unknown = sorted({t for t in task_names if t not in self._instruction_tokens})
        if unknown:
            raise ValueError(
                f"no instruction for task(s) {unknown}; known: {sorted(self._instruction_tokens)}"
            )
        return torch.stack([self._instruction_tokens[t] for t in task_names]).to(self.device)

    @abc.abstractmethod
    def sample_actions(self, batch: Batch) -> torch.Tensor:
        """Normalized action chunks (B, K, A) for a batch of observations."""

    @torch.no_grad()
    def predict_action_chunk(self, obs: Mapping[str, np.ndarray], task_names: list[str]) -> np.ndarray:
        was_training = self.training
        self.eval()
        try:
            batch = {"tokens": self.tokens_for(list(task_names))}
            for key in (self.config.obs_key, "proprio"):
                if key not in obs:
                    raise ValueError(
                        f"{self.config.obs_mode}-mode policy needs observation {key!r}, got {sorted(obs)}"
                    )
                batch[key] = torch.as_tensor(np.asarray(obs[key])).to(self.device)
            actions = self.normalizer.denormalize("action", self.sample_actions(batch))
            return actions.clamp(-1.0, 1.0).cpu().numpy().astype(np.float32)
        finally:
            self.train(was_training)

    def feature_specs(self) -> dict[str, FeatureSpec]:
        cfg = self.config
        return {
            "obs_tokens": FeatureSpec(cfg.n_layers, cfg.d_model, cfg.n_obs_tokens),
            "tokens": FeatureSpec(cfg.n_layers, cfg.d_model, self._type_ids.shape[0]),
        }
