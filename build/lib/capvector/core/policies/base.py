"""The policy interface (after LeRobot's `PreTrainedPolicy` and its config registry) and checkpoint I/O.

A policy type is one module: a `PolicyConfig` subclass and a `Policy` subclass registered together
under a type name with `@register_policy("name", ConfigClass)`. The policy owns everything that
depends on its architecture, so the trainer, the vector commands, the adapters and the evaluation
work on any registered type unchanged:

- its batches (`make_batcher`: dataset -> index -> batch dict) and normalizer (`fit_normalizer`);
- its loss (`compute_loss`: batch -> `PolicyOutput` with the total, named terms and features), and
  the randomness in it (noise, times, dropout) drawn from `generator` (`set_generator`: the trainer
  gives each run its own, seeded from the run's seed; None, the default, is torch's global RNG);
- named features for auxiliary objectives (`feature_specs`; e.g. ``obs_tokens``: per-layer hidden
  states at the observation tokens, ``tokens``: per-layer hidden states at every token);
- inference (`predict_action_chunk`: observations in env units + task names -> (B, K, A) actions).

Checkpoints are safetensors files whose metadata holds the config JSON (with its `type`) under
``CONFIG_METADATA_KEY``; `load_policy` dispatches on it. Files written before types existed have no
`type` and load as ``l1_chunk``. Other packages add types through the entry-point group
``capvector.policies`` (an entry point names a module or object whose import registers the type).
"""

from __future__ import annotations

import abc
import json
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
import torch
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, SerializeAsAny
from safetensors import safe_open
from safetensors.torch import load_file
from torch import nn

from capvector.core.training.device import resolve_device
from capvector.core.vectors.safetensors_io import Checkpoint, write_checkpoint

CONFIG_METADATA_KEY = "capvector.policy_config"
ENTRY_POINT_GROUP = "capvector.policies"
DEFAULT_POLICY_TYPE = "l1_chunk"
Batch = dict[str, torch.Tensor]
Batcher = Callable[[torch.Tensor], Batch]


class PolicyConfig(BaseModel):
    """Base of every policy config: its registered `type` and the observations it consumes."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)  # NaN/Inf in any field: refused at load

    type: str = Field(
        DEFAULT_POLICY_TYPE,
        description="registered policy type (built in: l1_chunk, flow; plugins add more); it decides "
        "which other fields exist",
    )
    obs_mode: Literal["state", "pixels"] = Field(
        "state", description="the observation the policy reads: `state` (39 numbers) or `pixels` (an image)"
    )
    image_size: int = Field(
        64, gt=0, description="side of the square input image in pixels (pixels mode only)"
    )

    @classmethod
    def class_for(cls, data: Mapping[str, Any]) -> type[PolicyConfig]:
        """The config class of the type `data` names (override paths are checked against its fields)."""
        return policy_class(data.get("type", DEFAULT_POLICY_TYPE)).config_class

    def to_dict(self) -> dict[str, Any]:
        """The config as a dict with a `model_type`, the form peft reads from `model.config`."""
        return {"model_type": f"capvector-{self.type}", **self.model_dump(mode="json")}


@dataclass(frozen=True)
class FeatureSpec:
    """A named feature a policy exposes: a list of `n_layers` tensors (B, n_tokens, dim)."""

    n_layers: int
    dim: int
    n_tokens: int


@dataclass
class PolicyOutput:
    """`loss` = sum of `terms`; `features[name]` is a per-layer list, only for the names asked for."""

    loss: torch.Tensor
    terms: dict[str, torch.Tensor]
    features: dict[str, list[torch.Tensor]] = field(default_factory=dict)


class Policy(nn.Module, abc.ABC):
    """A trainable, savable, evaluable policy; see the module docstring for the contract."""

    type_name: ClassVar[str] = ""
    config_class: ClassVar[type[PolicyConfig]] = PolicyConfig

    def __init__(self, config: PolicyConfig):
        super().__init__()
        self.config = config

    @property
    def device(self) -> torch.device:
        return next(self.buffers(), next(self.parameters())).device

    # ------------------------------------------------------------------ randomness
    @property
    def generator(self) -> torch.Generator | None:
        """Where `compute_loss` draws its randomness (noise, times, dropout masks); None: torch's
        global RNG. A policy whose loss is random must draw through it (`torch.randn(...,
        generator=self.generator)`), so that nothing else drawing from the global RNG (an auxiliary
        head's initialisation, a callback) changes the draws of a run."""
        return self.__dict__.get("_generator")

    def set_generator(self, generator: torch.Generator | None) -> None:
        """Draw the loss's randomness from `generator` (on the policy's device), or torch's global RNG
        (None). The trainer sets one per run and saves its state in each checkpoint."""
        self.__dict__["_generator"] = generator

    # ------------------------------------------------------------------ data
    @abc.abstractmethod
    def required_fields(self) -> list[str]:
        """Dataset fields training needs (checked before training starts)."""

    def check_dataset(self, dataset: Any) -> None:
        """Refuse a dataset this policy cannot train on, naming what is wrong."""
        missing = [k for k in self.required_fields() if k not in dataset.tensors]
        if missing:
            raise ValueError(
                f"dataset lacks field(s) {missing} needed to train a {self.type_name} policy "
                f"in {self.config.obs_mode} mode (has: {sorted(dataset.tensors)})"
            )

    @property
    @abc.abstractmethod
    def normalizer_fitted(self) -> bool:
        """Whether normalization statistics have been set (from data or a checkpoint)."""

    @abc.abstractmethod
    def fit_normalizer(self, tensors: Mapping[str, torch.Tensor]) -> None:
        """Set normalization statistics from a dataset's tensors."""

    @abc.abstractmethod
    def make_batcher(
        self, dataset: Any, device: torch.device, fields: Collection[str] = (), horizon: int | None = None
    ) -> tuple[int, Batcher]:
        """(number of samples, batcher): the batcher maps sample indices to a batch on `device`.

        `fields`: extra dataset fields to include per sample (e.g. ``privileged``); with `horizon`,
        ``<field>_future`` holds that field `horizon` steps later in the same episode.
        """

    # ------------------------------------------------------------------ training
    @abc.abstractmethod
    def feature_specs(self) -> dict[str, FeatureSpec]:
        """The named features `compute_loss` can return."""

    @abc.abstractmethod
    def compute_loss(self, batch: Batch, features: Collection[str] = ()) -> PolicyOutput:
        """The policy's own training loss on a batch from its batcher (terms named, e.g. ``action``)."""

    # ------------------------------------------------------------------ inference
    @abc.abstractmethod
    def predict_action_chunk(self, obs: Mapping[str, np.ndarray], task_names: list[str]) -> np.ndarray:
        """Observations (env units) -> action chunks (B, K, A) in env units, clipped to [-1, 1]."""


_REGISTRY: dict[str, type[Policy]] = {}
_entry_points_loaded = False


def register_policy(
    type_name: str, config_class: type[PolicyConfig]
) -> Callable[[type[Policy]], type[Policy]]:
    """Class decorator: register a policy class and its config under `type_name`."""

    def deco(cls: type[Policy]) -> type[Policy]:
        if type_name in _REGISTRY and _REGISTRY[type_name] is not cls:
            raise ValueError(f"policy type {type_name!r} is already registered ({_REGISTRY[type_name]})")
        if config_class.model_fields["type"].default != type_name:
            raise ValueError(
                f"{config_class.__name__}.type must default to {type_name!r} "
                f"(it is {config_class.model_fields['type'].default!r})"
            )
        cls.type_name = type_name
        cls.config_class = config_class
        _REGISTRY[type_name] = cls
        return cls

    return deco


def _load_entry_points() -> None:
    """Import every `capvector.policies` entry point once; importing registers the types."""
    global _entry_points_loaded
    if _entry_points_loaded:
        return
    _entry_points_loaded = True
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            ep.load()
        except Exception as exc:  # a broken plugin must say which one it is
            raise ImportError(
                f"policy plugin entry point {ep.name!r} ({ep.value}) failed to load: {exc}"
            ) from exc
        except SystemExit as exc:  # sys.exit() at import: it would end the command, silently, with its code
            raise ImportError(
                f"policy plugin entry point {ep.name!r} ({ep.value}) called sys.exit({exc.code!r}) at import"
            ) from None


def policy_class(type_name: str) -> type[Policy]:
    import capvector.core.policies  # noqa: F401  (registers the built-in types)

    if type_name not in _REGISTRY:
        _load_entry_points()
    if type_name not in _REGISTRY:
        raise ValueError(f"unknown policy type {type_name!r}; known: {policy_types()}")
    return _REGISTRY[type_name]


def policy_types() -> list[str]:
    import capvector.core.policies  # noqa: F401

    _load_entry_points()
    return sorted(_REGISTRY)


def parse_policy_config(value: Any) -> PolicyConfig:
    """A dict (or config) -> the config class registered for its `type` (default ``l1_chunk``)."""
    if isinstance(value, PolicyConfig):
        cls = policy_class(value.type).config_class
        return value if isinstance(value, cls) else cls.model_validate(value.model_dump())
    if isinstance(value, str):
        value = json.loads(value)
    if not isinstance(value, Mapping):
        raise ValueError(f"a policy config must be a mapping with a `type`, got {type(value).__name__}")
    type_name = value.get("type", DEFAULT_POLICY_TYPE)
    return policy_class(type_name).config_class.model_validate({**value, "type": type_name})


# A pipeline's or step's policy field: validated by the class its `type` names, dumped with all fields.
AnyPolicyConfig = Annotated[SerializeAsAny[PolicyConfig], BeforeValidator(parse_policy_config)]


def build_policy(config: PolicyConfig | Mapping, device: str | torch.device = "auto") -> Policy:
    config = parse_policy_config(config)
    return policy_class(config.type)(config).to(resolve_device(device))


def save_tensors_atomic(tensors: dict[str, torch.Tensor], path: Path, metadata: dict[str, str]) -> None:
    """One safetensors file, atomically (temporary name, fsync, rename), byte-for-byte reproducible.

    `safetensors.save_file` writes the metadata map in a per-process random order, so equal weights
    would get different content hashes (artifact ids); our writer keeps the (sorted) order given.
    """
    write_checkpoint(path, tensors, dict(sorted(metadata.items())), overwrite=True)


def save_policy(model: Policy, path: str | Path, metadata: Mapping[str, str] | None = None) -> Path:
    """Weights + buffers as safetensors, the config JSON (with its type) under CONFIG_METADATA_KEY."""
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


REGISTER_HINT = (
    "register a policy type: a PolicyConfig + Policy pair under @register_policy, declared as a "
    f"`{ENTRY_POINT_GROUP}` entry point (docs/guide/own-checkpoints.md, 'Your own policy type')"
)


class PolicyLoadError(ValueError):
    """A checkpoint no registered policy type can load (no config, or a type nobody registered)."""


def read_metadata(path: str | Path) -> dict[str, str]:
    """The safetensors metadata of a file, or of a checkpoint folder (single file or sharded)."""
    if Path(path).is_dir():
        return dict(Checkpoint(path).metadata)
    with safe_open(str(path), framework="pt") as fh:
        return dict(fh.metadata() or {})


def read_policy_config(path: str | Path) -> PolicyConfig:
    """The config a checkpoint's policy is built from: its weights' `CONFIG_METADATA_KEY` metadata, or,
    for a folder, its `config.json` when that names a `type` (LeRobot's layout). A type that no
    installed package registers, or no config at all, is refused in one line saying how to register one."""
    path = Path(path)
    meta = read_metadata(path)
    if CONFIG_METADATA_KEY in meta:
        value, where = json.loads(meta[CONFIG_METADATA_KEY]), f"{CONFIG_METADATA_KEY!r} metadata"
    elif path.is_dir() and isinstance(doc := _config_json(path), dict) and isinstance(doc.get("type"), str):
        value, where = doc, "config.json"
    else:
        found = "folder has no `type` in config.json and its weights have" if path.is_dir() else "file has"
        raise PolicyLoadError(
            f"{path}: not a capvector policy: the {found} no {CONFIG_METADATA_KEY!r} metadata naming a "
            f"policy type; {REGISTER_HINT}"
        )
    type_name = value.get("type", DEFAULT_POLICY_TYPE) if isinstance(value, dict) else None
    try:
        policy_class(type_name)
    except ValueError:
        raise PolicyLoadError(
            f"{path}: its {where} names policy type {type_name!r}, which no installed package registers "
            f"(known: {', '.join(policy_types())}); {REGISTER_HINT}"
        ) from None
    return parse_policy_config(value)


def _config_json(folder: Path) -> Any:
    try:
        return json.loads((folder / "config.json").read_text())
    except (OSError, ValueError):
        return None


def _read_tensors(path: str | Path) -> dict[str, torch.Tensor]:
    if Path(path).is_dir():  # a folder: one model.safetensors or shards with an index
        return dict(Checkpoint(path).items())  # each tensor read into a buffer of its own
    return load_file(str(path))


def load_policy_weights(model: nn.Module, path: str | Path) -> nn.Module:
    """Load a checkpoint into a model exactly; on any mismatch, list it and load nothing."""
    tensors = _read_tensors(path)
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


def load_policy(path: str | Path, device: str | torch.device = "auto") -> Policy:
    """Rebuild the policy its file's metadata names (type + config) and load its weights exactly."""
    config = read_policy_config(path)
    model = policy_class(config.type)(config)
    load_policy_weights(model, path)
    return model.to(resolve_device(device))
