"""The small VLA: instruction + (vision | state) + proprio tokens -> transformer -> action chunk.

Token layout (fixed length T, so one learned position table covers every input):
``[language (max_instruction_tokens) | obs tokens | proprio (1) | action queries (K)]``.

Obs tokens are either a conv stem's grid over the image (``pixels``) or, in ``state`` mode, the
39-number Meta-World observation split into five semantic groups, one token each: hand+gripper (0:4),
object 1 pose (4:11), object 2 pose (11:18), the previous frame of those (18:36) and the goal (36:39).
Grouping gives the ``spatial`` objective several tokens to align, as vision tokens do in pixels mode.

The backbone is a hand-written pre-norm transformer whose attention uses separate ``nn.Linear``
q/k/v/o projections, so adapters (LoRA) can target them by name. Parameter names are part of the
interface (capability vectors are per-tensor); the scheme is::

    language.embed.weight                    state.proj.<group>.{weight,bias}   (state mode)
    vision.stem.<2i>.{weight,bias}           vision.proj.{weight,bias}          (pixels mode)
    proprio.proj.{weight,bias}               embeddings.{position,action_queries,token_type.weight}
    backbone.layers.<i>.{norm1,norm2}.*      backbone.layers.<i>.attn.{q,k,v,o}_proj.*
    backbone.layers.<i>.mlp.{fc1,fc2}.*      backbone.norm.*
    action_head.proj.{weight,bias}           normalizer.{state,proprio,action}_{mean,std}, normalizer.fitted
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from safetensors import safe_open
from safetensors.torch import load_file
from torch import nn

from capvector_core import tokenizer
from capvector_core.device import resolve_device
from capvector_core.safetensors_io import write_checkpoint

CONFIG_METADATA_KEY = "capvector.policy_config"
STATE_GROUPS: dict[str, tuple[int, int]] = {
    "hand": (0, 4),
    "obj1": (4, 11),
    "obj2": (11, 18),
    "prev": (18, 36),
    "goal": (36, 39),
}
TOKEN_TYPES = ("language", "obs", "proprio", "action")


class PolicyConfig(BaseModel):
    """Architecture and input settings; stored in every checkpoint so a file rebuilds its model."""

    model_config = ConfigDict(extra="forbid")

    obs_mode: Literal["state", "pixels"] = "state"
    d_model: int = Field(128, gt=0)
    n_layers: int = Field(4, gt=0)
    n_heads: int = Field(4, gt=0)
    ffn_mult: int = Field(4, gt=0)
    dropout: float = Field(0.0, ge=0.0, lt=1.0)
    chunk_size: int = Field(8, gt=0, description="K: actions predicted per call")
    image_size: int = Field(64, gt=0)
    stem_channels: list[int] = Field(default_factory=lambda: [32, 64, 64, 128])
    state_tokens: Literal["grouped", "single"] = "grouped"
    vocab_size: int = Field(512, ge=2)
    max_instruction_tokens: int = Field(12, gt=0)
    state_dim: int = Field(39, gt=0)
    proprio_dim: int = Field(4, gt=0)
    action_dim: int = Field(4, gt=0)

    @field_validator("stem_channels")
    @classmethod
    def _channels_positive(cls, value: list[int]) -> list[int]:
        if not value or any(c <= 0 for c in value):
            raise ValueError(f"stem_channels must be a non-empty list of positive ints, got {value}")
        return value

    @model_validator(mode="after")
    def _consistent(self) -> PolicyConfig:
        if self.d_model % self.n_heads:
            raise ValueError(f"d_model ({self.d_model}) must be divisible by n_heads ({self.n_heads})")
        if self.obs_mode == "pixels":
            factor = 2 ** len(self.stem_channels)
            if self.image_size % factor:
                raise ValueError(
                    f"image_size ({self.image_size}) must be divisible by 2**len(stem_channels) = {factor} "
                    "(each stem conv halves the image)"
                )
        if self.state_tokens == "grouped" and self.state_dim != 39:
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
        return len(STATE_GROUPS) if self.state_tokens == "grouped" else 1

    @property
    def n_tokens(self) -> int:
        return self.max_instruction_tokens + self.n_obs_tokens + 1 + self.chunk_size

    def token_slices(self) -> dict[str, slice]:
        """Positions of each token kind; the obs kind is named "vision" or "state" by mode."""
        lang = self.max_instruction_tokens
        obs = lang + self.n_obs_tokens
        obs_name = "vision" if self.obs_mode == "pixels" else "state"
        return {
            "language": slice(0, lang),
            obs_name: slice(lang, obs),
            "proprio": slice(obs, obs + 1),
            "action": slice(obs + 1, obs + 1 + self.chunk_size),
        }


class Normalizer(nn.Module):
    """Input/output statistics as buffers, so a saved policy acts in env units without its dataset."""

    def __init__(self, config: PolicyConfig):
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

    def normalize(self, key: str, x: torch.Tensor) -> torch.Tensor:
        return (x - getattr(self, f"{key}_mean")) / getattr(self, f"{key}_std")

    def denormalize(self, key: str, x: torch.Tensor) -> torch.Tensor:
        return x * getattr(self, f"{key}_std") + getattr(self, f"{key}_mean")


class Attention(nn.Module):
    def __init__(self, d_model: int, n_heads: int, dropout: float):
        super().__init__()
        self.n_heads = n_heads
        self.dropout = dropout
        self.q_proj = nn.Linear(d_model, d_model)
        self.k_proj = nn.Linear(d_model, d_model)
        self.v_proj = nn.Linear(d_model, d_model)
        self.o_proj = nn.Linear(d_model, d_model)

    def forward(self, x: torch.Tensor, key_mask: torch.Tensor) -> torch.Tensor:
        b, t, d = x.shape
        h = self.n_heads

        def split(y: torch.Tensor) -> torch.Tensor:
            return y.view(b, t, h, d // h).transpose(1, 2)

        out = F.scaled_dot_product_attention(
            split(self.q_proj(x)),
            split(self.k_proj(x)),
            split(self.v_proj(x)),
            attn_mask=key_mask[:, None, None, :],
            dropout_p=self.dropout if self.training else 0.0,
        )
        return self.o_proj(out.transpose(1, 2).reshape(b, t, d))


class MLP(nn.Module):
    def __init__(self, d_model: int, hidden: int, dropout: float):
        super().__init__()
        self.fc1 = nn.Linear(d_model, hidden)
        self.fc2 = nn.Linear(hidden, d_model)
        self.drop = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.drop(self.fc2(F.gelu(self.fc1(x))))


class Block(nn.Module):
    def __init__(self, config: PolicyConfig):
        super().__init__()
        d = config.d_model
        self.norm1 = nn.LayerNorm(d)
        self.attn = Attention(d, config.n_heads, config.dropout)
        self.norm2 = nn.LayerNorm(d)
        self.mlp = MLP(d, d * config.ffn_mult, config.dropout)
        self.drop = nn.Dropout(config.dropout)

    def forward(self, x: torch.Tensor, key_mask: torch.Tensor) -> torch.Tensor:
        x = x + self.drop(self.attn(self.norm1(x), key_mask))
        return x + self.mlp(self.norm2(x))


class Backbone(nn.Module):
    def __init__(self, config: PolicyConfig):
        super().__init__()
        self.layers = nn.ModuleList(Block(config) for _ in range(config.n_layers))
        self.norm = nn.LayerNorm(config.d_model)


class LanguageEncoder(nn.Module):
    def __init__(self, config: PolicyConfig):
        super().__init__()
        self.embed = nn.Embedding(config.vocab_size, config.d_model, padding_idx=tokenizer.PAD_ID)


class VisionEncoder(nn.Module):
    """Strided 3x3 convs (each halves the image) -> grid of tokens -> linear to d_model."""

    def __init__(self, config: PolicyConfig):
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


class StateEncoder(nn.Module):
    def __init__(self, config: PolicyConfig):
        super().__init__()
        if config.state_tokens == "grouped":
            self.groups = dict(STATE_GROUPS)
        else:
            self.groups = {"all": (0, config.state_dim)}
        self.proj = nn.ModuleDict(
            {name: nn.Linear(b - a, config.d_model) for name, (a, b) in self.groups.items()}
        )

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        return torch.stack([self.proj[name](state[:, a:b]) for name, (a, b) in self.groups.items()], dim=1)


class ActionHead(nn.Module):
    def __init__(self, config: PolicyConfig):
        super().__init__()
        self.proj = nn.Linear(config.d_model, config.action_dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x)


class Embeddings(nn.Module):
    def __init__(self, config: PolicyConfig):
        super().__init__()
        self.position = nn.Parameter(torch.randn(config.n_tokens, config.d_model) * 0.02)
        self.action_queries = nn.Parameter(torch.randn(config.chunk_size, config.d_model) * 0.02)
        self.token_type = nn.Embedding(len(TOKEN_TYPES), config.d_model)
        nn.init.normal_(self.token_type.weight, std=0.02)


class VLAPolicy(nn.Module):
    """See the module docstring for the token layout and parameter names."""

    def __init__(self, config: PolicyConfig):
        super().__init__()
        self.config = config
        self.language = LanguageEncoder(config)
        if config.obs_mode == "pixels":
            self.vision = VisionEncoder(config)
        else:
            self.state = StateEncoder(config)
        self.proprio = nn.Module()
        self.proprio.proj = nn.Linear(config.proprio_dim, config.d_model)
        self.embeddings = Embeddings(config)
        self.backbone = Backbone(config)
        self.action_head = ActionHead(config)
        self.normalizer = Normalizer(config)
        nn.init.normal_(self.language.embed.weight, std=0.02)
        with torch.no_grad():
            self.language.embed.weight[tokenizer.PAD_ID].zero_()
        type_ids = torch.cat(
            [torch.full((s.stop - s.start,), i) for i, s in enumerate(config.token_slices().values())]
        )
        self.register_buffer("_type_ids", type_ids, persistent=False)
        self._instruction_tokens: dict[str, torch.Tensor] = {}

    @property
    def device(self) -> torch.device:
        return self.normalizer.fitted.device

    def forward(self, batch: Mapping[str, torch.Tensor]) -> dict:
        """batch: "tokens" (B,L) int64, "proprio" (B,4) and "state" (B,39) or "image" (B,H,W,3) uint8,
        all in env units. Returns normalized "actions" (B,K,A), per-layer "hidden", "token_slices"."""
        cfg = self.config
        tokens = batch["tokens"]
        if tokens.shape[1] != cfg.max_instruction_tokens:
            raise ValueError(
                f"tokens must have {cfg.max_instruction_tokens} columns, got {tuple(tokens.shape)}"
            )
        b = tokens.shape[0]
        lang = self.language.embed(tokens)
        if cfg.obs_mode == "pixels":
            obs = self.vision(batch["image"])
        else:
            obs = self.state(self.normalizer.normalize("state", batch["state"]))
        proprio = self.proprio.proj(self.normalizer.normalize("proprio", batch["proprio"]))[:, None]
        queries = self.embeddings.action_queries.expand(b, -1, -1)
        x = torch.cat([lang, obs, proprio, queries], dim=1)
        x = x + self.embeddings.position + self.embeddings.token_type(self._type_ids)
        key_mask = torch.cat(
            [
                tokens != tokenizer.PAD_ID,
                torch.ones(b, x.shape[1] - tokens.shape[1], dtype=torch.bool, device=x.device),
            ],
            dim=1,
        )
        hidden = []
        for layer in self.backbone.layers:
            x = layer(x, key_mask)
            hidden.append(x)
        slices = cfg.token_slices()
        actions = self.action_head(self.backbone.norm(x[:, slices["action"]]))
        return {"actions": actions, "hidden": hidden, "token_slices": slices}

    def action_loss(self, predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """L1 between normalized predictions and env-unit targets (B,K,A), in normalized space."""
        return F.l1_loss(predicted, self.normalizer.normalize("action", target))

    def set_instructions(self, instructions: Mapping[str, str]) -> None:
        """Tokenize task -> instruction once; used by act()."""
        cfg = self.config
        self._instruction_tokens = {
            task: torch.tensor(tokenizer.encode(text, cfg.vocab_size, cfg.max_instruction_tokens))
            for task, text in instructions.items()
        }

    def tokens_for(self, task_names: list[str]) -> torch.Tensor:
        if not self._instruction_tokens:
            from capvector_core.metaworld_tasks import INSTRUCTIONS  # lazy: keeps policy usable alone

            self.set_instructions(INSTRUCTIONS)
        unknown = sorted({t for t in task_names if t not in self._instruction_tokens})
        if unknown:
            raise ValueError(
                f"no instruction for task(s) {unknown}; known: {sorted(self._instruction_tokens)}"
            )
        return torch.stack([self._instruction_tokens[t] for t in task_names]).to(self.device)

    @torch.no_grad()
    def act(self, obs: Mapping[str, np.ndarray], task_names: list[str]) -> np.ndarray:
        """Observations (env units) -> action chunks (B,K,A) in env units, clipped to [-1, 1]."""
        was_training = self.training
        self.eval()
        try:
            batch = {"tokens": self.tokens_for(list(task_names))}
            needed = ("image", "proprio") if self.config.obs_mode == "pixels" else ("state", "proprio")
            for key in needed:
                if key not in obs:
                    raise ValueError(
                        f"{self.config.obs_mode}-mode policy needs observation {key!r}, got {sorted(obs)}"
                    )
                batch[key] = torch.as_tensor(np.asarray(obs[key])).to(self.device)
            actions = self.normalizer.denormalize("action", self(batch)["actions"])
            return actions.clamp(-1.0, 1.0).cpu().numpy().astype(np.float32)
        finally:
            self.train(was_training)


def build_policy(config: PolicyConfig | Mapping, device: str | torch.device = "auto") -> VLAPolicy:
    config = config if isinstance(config, PolicyConfig) else PolicyConfig.model_validate(config)
    return VLAPolicy(config).to(resolve_device(device))


def save_tensors_atomic(tensors: dict[str, torch.Tensor], path: Path, metadata: dict[str, str]) -> None:
    """One safetensors file, atomically (temporary name, fsync, rename), byte-for-byte reproducible.

    `safetensors.save_file` writes the metadata map in a per-process random order, so equal weights
    would get different content hashes (artifact ids); our writer keeps the (sorted) order given.
    """
    write_checkpoint(path, tensors, dict(sorted(metadata.items())), overwrite=True)


def save_policy(model: VLAPolicy, path: str | Path, metadata: Mapping[str, str] | None = None) -> Path:
    """Weights + buffers as safetensors, PolicyConfig JSON under CONFIG_METADATA_KEY; atomic."""
    path = Path(path)
    extra = dict(metadata or {})
    bad = [k for k, v in extra.items() if not isinstance(k, str) or not isinstance(v, str)]
    if bad:
        raise ValueError(f"safetensors metadata must be str -> str; offending keys: {bad}")
    if CONFIG_METADATA_KEY in extra:
        raise ValueError(f"metadata key {CONFIG_METADATA_KEY!r} is reserved for the policy config")
    extra[CONFIG_METADATA_KEY] = model.config.model_dump_json()
    tensors = {k: v.detach().to("cpu").contiguous() for k, v in model.state_dict().items()}
    path.parent.mkdir(parents=True, exist_ok=True)
    save_tensors_atomic(tensors, path, extra)
    return path


def read_metadata(path: str | Path) -> dict[str, str]:
    with safe_open(str(path), framework="pt") as fh:
        return dict(fh.metadata() or {})


def read_policy_config(path: str | Path) -> PolicyConfig:
    meta = read_metadata(path)
    if CONFIG_METADATA_KEY not in meta:
        raise ValueError(
            f"{path}: no {CONFIG_METADATA_KEY!r} in safetensors metadata; not a capvector policy file"
        )
    return PolicyConfig.model_validate_json(meta[CONFIG_METADATA_KEY])


def load_policy_weights(model: nn.Module, path: str | Path) -> nn.Module:
    """Load a checkpoint into a model exactly; on any mismatch, list it and load nothing."""
    tensors = load_file(str(path))
    expected = model.state_dict()
    missing = sorted(set(expected) - set(tensors))
    unexpected = sorted(set(tensors) - set(expected))
    shapes = [
        f"{k}: checkpoint {tuple(tensors[k].shape)} vs model {tuple(v.shape)}"
        for k, v in expected.items()
        if k in tensors and tensors[k].shape != v.shape
    ]
    if missing or unexpected or shapes:
        note = ""
        meta = read_metadata(path)
        config = getattr(model, "config", None)
        if CONFIG_METADATA_KEY in meta and isinstance(config, BaseModel):
            theirs = json.loads(meta[CONFIG_METADATA_KEY])
            ours = config.model_dump(mode="json")
            diff = {
                k: (theirs.get(k), ours.get(k))
                for k in sorted(set(theirs) | set(ours))
                if theirs.get(k) != ours.get(k)
            }
            note = f"; config differences (checkpoint, model): {diff}"
        raise ValueError(
            f"checkpoint {path} does not match the model: missing keys {missing}, "
            f"unexpected keys {unexpected}, "
            f"shape mismatches {shapes}{note}"
        )
    model.load_state_dict(tensors, strict=True)
    return model


def load_policy(path: str | Path, device: str | torch.device = "auto") -> VLAPolicy:
    """Rebuild the model from the config in the file's metadata and load its weights exactly."""
    model = VLAPolicy(read_policy_config(path))
    load_policy_weights(model, path)
    return model.to(resolve_device(device))
