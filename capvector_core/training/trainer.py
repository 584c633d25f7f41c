"""The training loop for any `Policy`: SFT, SFT + auxiliary objective, plus an extra-loss hook.

The policy owns its batches and its loss (`capvector.core.policies.base`); this module keeps only the loop:
schedule, clipping, non-finite guards, checkpoints, exact resume and the extra losses.

Randomness: three streams per run, all from its seed, none consuming another's draws: the batch
indices (a generator seeded with the seed), the policy's own randomness in its loss (flow matching's
noise and times, dropout masks: `Policy.generator`, a generator on the training device seeded from the
seed for that purpose alone) and the auxiliary heads' initialisation (a generator of their own, seeded
with the seed; torch's global RNG is left as it was). So θ_ao and θ_ft, two runs from the same start
with the same seed, train on the same batches with the same noise whichever objective one adds; with
the objective's weight 0 they are the same weights, bit for bit. torch's global RNG is still seeded
with the seed (for whatever else draws from it: a plugin policy's loss, adapter dropout).

Exact resume: every checkpoint holds the policy and aux-head weights (safetensors), the optimizer
state, the batch and policy generators' states and torch's global RNG states, the step, and the state of
an `after_optimizer_step` hook that has one (AdaLoRA's rank allocator). The
learning rate is a pure function of the step (linear warm-up then cosine to ``min_lr_ratio``), so it
needs no state of its own. ``train`` resumes from the newest complete checkpoint in ``run_dir``; a run
killed at any point and rerun ends with the same weights, bit for bit, as an uninterrupted one with the
same seed. A checkpoint without the policy generator's state (written before it had one) is passed
over. Only the same run resumes: a checkpoint records its run's origin (the dataset's content hash and
a digest of the starting weights) beside its TrainConfig, and one from other data or another start is
an error.

Lost files are recomputed, never a dead end: a checkpoint whose files are missing or unreadable, or
one past a kept snapshot that is gone, is passed over for the newest older one that is intact (a
snapshot at the resume step itself is written again from its weights); with none, or without the
loss curve, training starts over. Checkpoints past the resume point are removed.

Layout of ``run_dir``::

    checkpoints/step_XXXXXXXX/{policy.safetensors, aux.safetensors, trainer_state.pt, train_config.json}
    loss_curve.jsonl      one row per log interval: step, mean loss terms, lr, grad_norm, time
    snapshots/step_XXXXXXXX.safetensors  the policy at each of ``snapshot_steps`` (kept, unlike checkpoints)
    policy.safetensors    final policy weights (config in metadata)
    aux_heads.safetensors final auxiliary heads (only with an aux objective)
    result.json           TrainResult
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import shutil
import time
from collections.abc import Callable, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any, Protocol, runtime_checkable

import torch
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from safetensors.torch import load_file, save_file
from torch import nn

from capvector.core.policies.base import Policy, load_policy_weights, save_policy, save_tensors_atomic
from capvector.core.training.aux_objectives import AuxObjective, build_objective, get_objective
from capvector.core.training.device import resolve_device, run_environment
from capvector.core.training.execution import ExecutionOnly, execution_only_fields
from capvector.durable import fsync_dir, fsync_files, write_atomic

ExtraLoss = Callable[[nn.Module], torch.Tensor]
SnapshotWriter = Callable[[Any, Path], Any]
"""(policy, path) -> writes the policy kept at a snapshot step (default `save_policy`)."""
_CKPT = re.compile(r"^step_(\d{8})$")


class AuxConfig(BaseModel):
    """An auxiliary objective added to the action loss (capvector.core.training.aux_objectives)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)  # a NaN/inf weight: refused here
    name: str = Field(
        description="registered objective: `spatial` (align obs tokens with 3D scene features), "
        "`spatial_depth` (pixels: each vision token with its patch's 3D point) or `dynamics` (predict "
        "the privileged state a few steps ahead)"
    )
    weight: float = Field(
        0.5,
        ge=0.0,
        description="loss weight (Spatial Forcing's default is 0.5); 0: computed and logged but trains "
        "nothing (the run is plain SFT's, bit for bit)",
    )
    params: dict[str, Any] = Field(
        default_factory=dict,
        description="the objective's own settings, checked by its Params model (e.g. dynamics: horizon, "
        "layer, hidden_dim; spatial: layer, pooling, hidden_dim, feature_dim, fourier_scale, seed); "
        "{}: its defaults",
    )

    @field_validator("name")
    @classmethod
    def _known(cls, value: str) -> str:
        get_objective(value)
        return value


class TrainConfig(BaseModel):
    """One training run: AdamW, linear warm-up then cosine decay, gradient clipping, exact resume."""

    # lr, weight_decay, min_lr_ratio, grad_clip: finite numbers (NaN or inf is refused, naming the field)
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    steps: int = Field(1000, gt=0, description="optimizer steps of the run (its final budget)")
    batch_size: int = Field(
        64, gt=0, description="samples per step, drawn from the demonstrations (at most the dataset's size)"
    )
    lr: float = Field(
        3e-4, gt=0, description="peak learning rate (AdamW), reached after warmup_steps, then cosine decay"
    )
    weight_decay: float = Field(
        0.01, ge=0, description="AdamW decoupled weight decay, on matrices only (not biases or norms)"
    )
    warmup_steps: int = Field(
        100, ge=0, description="steps of linear warm-up to lr (must be < steps); 0: start at lr"
    )
    min_lr_ratio: float = Field(
        0.1, ge=0, le=1, description="the cosine decay ends at lr × this (0-1; 1: constant after warm-up)"
    )
    grad_clip: float | None = Field(
        1.0, gt=0, description="clip the global gradient L2 norm to this; null: no clipping"
    )
    seed: int = Field(
        0,
        description="seed of initialisation (from scratch, adapters, auxiliary heads), batch order and the "
        "policy's randomness (dropout, flow matching's noise and times), each a stream of its own; the "
        "pipeline replaces it downstream by each of `seeds` (a study also in extraction, by its draws)",
    )
    checkpoint_every: Annotated[
        int, ExecutionOnly("resume is exact: the weights are the same whenever checkpoints are written")
    ] = Field(
        500,
        gt=0,
        description="steps between resumable checkpoints; speed only, never the result (not in the cache "
        "key)",
    )
    snapshot_steps: list[int] = Field(
        default_factory=list,
        description="budgets (0 < step < steps) at which the policy is also kept as it is then "
        "(success-vs-steps curves, early endpoints); a study sets them itself",
    )
    keep_checkpoints: Annotated[int, ExecutionOnly("disk use only: older checkpoints are only deleted")] = (
        Field(
            2,
            gt=0,
            description="newest resumable checkpoints kept on disk; older ones are deleted (not in the "
            "cache key)",
        )
    )
    log_every: int = Field(10, gt=0, description="steps per loss-curve row (mean loss terms, lr, grad norm)")
    aux: AuxConfig | None = Field(
        None,
        description="auxiliary objective trained alongside the action loss; null: plain SFT. The pipeline "
        "sets it in extraction and downstream (the top-level `aux` for θ_ao and the aux arm, null for the "
        "others) and uses it as given for pretraining",
    )
    fit_normalizer: bool | None = Field(
        None,
        description="set policy normalization stats from the data; None: only if the policy has none yet",
    )
    device: Annotated[str, ExecutionOnly("where it trains: the same computation, up to float rounding")] = (
        Field(
            "auto",
            description="torch device: auto (CUDA when available, else CPU), cpu, cuda or cuda:N; not in the "
            "cache key (the checkpoint's record says which device trained it); bit-identical resume needs "
            "the same device",
        )
    )
    num_threads: Annotated[
        int | None, ExecutionOnly("how fast on a CPU: the same computation, up to float rounding")
    ] = Field(
        None,
        gt=0,
        description="torch CPU threads of the run; null: torch's default; speed only (not in the cache key; "
        "the checkpoint's record has the count used)",
    )

    @model_validator(mode="after")
    def _warmup(self) -> TrainConfig:
        if self.warmup_steps >= self.steps:
            raise ValueError(f"warmup_steps ({self.warmup_steps}) must be < steps ({self.steps})")
        bad = [s for s in self.snapshot_steps if not 0 < s < self.steps]
        if bad or len(set(self.snapshot_steps)) != len(self.snapshot_steps):
            raise ValueError(
                f"snapshot_steps {self.snapshot_steps} must be distinct and strictly between 0 and "
                f"steps ({self.steps}): the final weights are the run's result"
            )
        return self


# Fields allowed to differ on resume: they change neither the batches nor the schedule. Those not in the
# cache key (capvector.core.training.execution), and log_every (it changes only how the curve is averaged).
# (Another device or thread count can change float rounding: bit-identical resume needs those to match.)
_RESUME_FREE = set(execution_only_fields(TrainConfig)) | {"log_every"}


class TrainResult(BaseModel):
    weights_path: Path
    aux_weights_path: Path | None
    loss_curve_path: Path
    steps: int
    resumed_from_step: int
    train_seconds: float  # over all invocations of this run (the loop only, checkpoints included)
    steps_per_s: float
    samples_per_s: float
    final_loss: float
    snapshots: dict[int, Path] = {}  # step -> the policy's weights after that many steps
    # where this invocation trained (capvector.core.training.device.run_environment): resolved device,
    # threads, torch
    execution: dict[str, Any] = {}


def lr_at(step: int, config: TrainConfig) -> float:
    """Learning rate for 0-based step: linear warm-up, then cosine decay to lr * min_lr_ratio."""
    if step < config.warmup_steps:
        return config.lr * (step + 1) / config.warmup_steps
    progress = (step - config.warmup_steps) / max(1, config.steps - config.warmup_steps)
    cosine = 0.5 * (1.0 + math.cos(math.pi * min(1.0, progress)))
    return config.lr * (config.min_lr_ratio + (1.0 - config.min_lr_ratio) * cosine)


def _check_dataset(dataset: Any, policy: Policy, objective: AuxObjective | None, batch_size: int) -> None:
    policy.check_dataset(dataset)
    tensors = dataset.tensors
    if objective is not None:
        missing = [k for k in objective.required_fields() if k not in tensors]
        if missing:
            raise ValueError(
                f"auxiliary objective {objective.name!r} needs dataset field(s) {missing}, "
                f"which this dataset lacks (has: {sorted(tensors)})"
            )
    n = tensors["action"].shape[0]
    if batch_size > n:
        raise ValueError(f"batch_size ({batch_size}) is larger than the dataset ({n} samples)")


def _checkpoints(run_dir: Path) -> list[tuple[int, Path]]:
    root = run_dir / "checkpoints"
    if not root.is_dir():
        return []
    found = [(int(m.group(1)), p) for p in root.iterdir() if (m := _CKPT.match(p.name)) and p.is_dir()]
    return sorted(found)


class _Run:
    """State of one training invocation (kept together so checkpointing sees all of it), and the steps
    of its loop: schedule, loss, clipping, and the bookkeeping after each step."""

    def __init__(
        self, policy, objective, dataset, config, run_dir, device, extra_losses, step_hook=None, snaps=None
    ):
        """On `device` in train mode, with a fresh optimizer and the run's seeded generators."""
        policy.to(device).train()
        # the policy's, then the heads': the order the gradient norm sums in (bit for bit)
        self.params = [p for p in policy.parameters() if p.requires_grad]
        if objective is not None:
            objective.to(device).train()
            self.params += list(objective.parameters())
        self.optimizer = torch.optim.AdamW(_param_groups(self.params, config.weight_decay), lr=config.lr)
        self.generator = torch.Generator().manual_seed(config.seed)
        # the policy's own randomness (Policy.generator), on `device`
        self.sampling = torch.Generator(device=device).manual_seed(_stream_seed(config.seed, "policy"))
        self.origin = {"data": str(getattr(dataset, "content_hash", None)), "start": _weights_digest(policy)}
        self.policy, self.objective, self.extra_losses = policy, objective, extra_losses
        self.step_hook = step_hook
        self.config, self.run_dir, self.device = config, run_dir, device
        self.step = 0
        self.train_seconds = 0.0
        self.lap_start = 0.0  # when the timed stretch now running began (time.perf_counter)
        self.write_snapshot: SnapshotWriter = snaps or save_policy  # snaps: the run's SnapshotWriter

    def schedule(self, step: int) -> float:
        """Set the learning rate of 0-based `step` (a pure function of it: nothing to resume)."""
        lr = lr_at(step, self.config)
        for group in self.optimizer.param_groups:
            group["lr"] = lr
        return lr

    def loss(self, batch: Mapping, curve: _Curve) -> tuple[torch.Tensor, torch.Tensor]:
        """The step's total loss, and the values of it and its terms: the policy's, the objective's, the
        extra losses'. The first step names the curve's columns (a clash is refused before a NaN)."""
        out = self.policy.compute_loss(batch, self.objective.feature_names if self.objective else ())
        terms = dict(out.terms)
        if self.objective is not None:
            terms[self.objective.name] = _aux_term(
                self.objective, self.config.aux.weight, out.features, batch
            )
        for name, fn in self.extra_losses.items():
            terms[name] = fn(self.policy)
        curve.name_columns(out.terms, self.objective, self.extra_losses)
        return _total_loss(terms, self.step)

    def clip_gradients(self) -> torch.Tensor:
        """Clip to ``grad_clip`` (when set); the global gradient norm before clipping, for the curve."""
        if self.config.grad_clip is not None:
            return torch.nn.utils.clip_grad_norm_(self.params, self.config.grad_clip)
        return torch.linalg.vector_norm(
            torch.stack([p.grad.norm() for p in self.params if p.grad is not None])
        )

    def after_step(self, curve: _Curve, lr: float, on_checkpoint: CheckpointHook | None) -> None:
        """A curve row, a snapshot and a checkpoint, each when the step just done is due one."""
        done = self.step == self.config.steps
        if self.step % self.config.log_every == 0 or done:
            self.lap()
            curve.write_row(self.step, lr, self.train_seconds)
        if self.step in self.config.snapshot_steps:
            self.lap()
            self.snapshot(self.step)
            self.lap_start = time.perf_counter()  # writing a snapshot is not a training step's time
        if self.step % self.config.checkpoint_every == 0 or done:
            self.checkpoint(curve, on_checkpoint)

    def snapshot(self, step: int) -> None:
        """The policy as it stands, kept at `snapshot_path` by the run's writer (an adapter run's writes its
        merged weights); any randomness the writer draws is not the run's (RNG states forked)."""
        cuda = [self.device] if torch.device(self.device).type == "cuda" else []
        with torch.random.fork_rng(devices=cuda):
            self.write_snapshot(self.policy, snapshot_path(self.run_dir, step))

    def lap(self) -> None:
        """Add the time since the last lap to ``train_seconds`` and start the next."""
        now = time.perf_counter()
        self.train_seconds += now - self.lap_start
        self.lap_start = now

    def checkpoint(self, curve: _Curve, on_checkpoint: CheckpointHook | None) -> None:
        """A resumable checkpoint, the curve durable up to it; writing it and the hook are not timed."""
        self.lap()
        curve.sync()
        saved = self.save()
        if on_checkpoint is not None:
            on_checkpoint(self.step, saved)
        self.lap_start = time.perf_counter()

    def save(self) -> Path:
        """Write the checkpoint of this step (once) and return its folder."""
        root = self.run_dir / "checkpoints"
        root.mkdir(parents=True, exist_ok=True)
        final = root / f"step_{self.step:08d}"
        if final.exists():
            return final
        tmp = root / f".tmp-step_{self.step:08d}"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        save_policy(self.policy, tmp / "policy.safetensors")
        if self.objective is not None:
            save_file(_cpu_state(self.objective), str(tmp / "aux.safetensors"))
        state = {
            "step": self.step,
            "origin": self.origin,
            "train_seconds": self.train_seconds,
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "sampling": self.sampling.get_state(),
            "sampling_device": self.sampling.device.type,
            "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else [],
        }
        if isinstance(self.step_hook, StatefulStepHook):
            state["step_hook"] = self.step_hook.state_dict()
        torch.save(state, tmp / "trainer_state.pt")
        (tmp / "train_config.json").write_text(self.config.model_dump_json(indent=1))
        fsync_files(tmp)
        os.replace(tmp, final)
        fsync_dir(root)
        for _, old in _checkpoints(self.run_dir)[: -self.config.keep_checkpoints]:
            shutil.rmtree(old, ignore_errors=True)
        return final

    def check_config(self, path: Path, saved: TrainConfig | None = None) -> None:
        """Refuse a checkpoint written under another TrainConfig (an error, not a lost file)."""
        if saved is None:
            saved = TrainConfig.model_validate_json((path / "train_config.json").read_text())
        ours, theirs = self.config.model_dump(), saved.model_dump()
        diff = sorted(k for k in ours if k not in _RESUME_FREE and ours[k] != theirs.get(k))
        if diff:
            raise ValueError(
                f"cannot resume from {path}: its TrainConfig differs in {diff} "
                f"(checkpoint {[theirs.get(k) for k in diff]}, now {[ours[k] for k in diff]}); "
                "use a new run_dir for a different configuration"
            )

    def check_origin(self, path: Path, state: dict[str, Any]) -> None:
        """Refuse a checkpoint of another run: other data, or other starting weights, in this run_dir."""
        theirs = state.get("origin")
        if theirs != self.origin:
            differs = (
                "it records no origin (written before origins were)"
                if theirs is None
                else "its "
                + " and ".join(
                    f"{k} ({theirs.get(k)} vs {v})" for k, v in self.origin.items() if theirs.get(k) != v
                )
                + " differ"
            )
            raise ValueError(
                f"cannot resume from {path}: {differs}; this run_dir belongs to another run, "
                "use a new run_dir"
            )

    def read(self, path: Path) -> dict[str, Any]:
        """Every file of a checkpoint, read before anything is changed (raises if one is lost)."""
        state = torch.load(path / "trainer_state.pt", weights_only=True, map_location="cpu")
        if "sampling" not in state:  # its policy drew from the global RNG: cannot be continued exactly
            raise KeyError(f"{path.name} has no policy generator state (written before there was one)")
        if isinstance(self.step_hook, StatefulStepHook) and "step_hook" not in state:
            raise KeyError(f"{path.name} has no state of the after_optimizer_step hook")
        return {
            "policy": load_file(str(path / "policy.safetensors")),
            "aux": load_file(str(path / "aux.safetensors")) if self.objective is not None else None,
            "state": state,
        }

    def load(self, path: Path, read: dict[str, Any] | None = None) -> None:
        if read is None:
            self.check_config(path)
            read = self.read(path)
        load_policy_weights(self.policy, path / "policy.safetensors")
        if self.objective is not None:
            self.objective.load_state_dict(read["aux"], strict=True)
        state = read["state"]
        self.check_origin(path, state)
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
        if state["sampling_device"] == self.sampling.device.type:
            self.sampling.set_state(state["sampling"])
        else:  # another kind of device, another kind of generator: the same run, not the same draws
            seed = _stream_seed(self.config.seed, f"policy/resumed at {int(state['step'])}")
            self.sampling.manual_seed(seed)
        torch.set_rng_state(state["torch_rng"])
        if state["cuda_rng"] and torch.cuda.is_available():
            torch.cuda.set_rng_state_all(state["cuda_rng"])
        if isinstance(self.step_hook, StatefulStepHook):
            self.step_hook.load_state_dict(state["step_hook"])
        self.step = int(state["step"])
        self.train_seconds = float(state["train_seconds"])

    def resume(self, snapshot_at: set[int], curve_path: Path) -> str:
        """Load the newest usable checkpoint of the run dir (see the module's docstring); says what was
        passed over ("" when nothing was)."""
        passed: list[str] = []
        chosen = 0
        checkpoints = _checkpoints(self.run_dir)
        usable = checkpoints
        if checkpoints and not curve_path.exists():
            passed.append(f"{curve_path.name} missing")
            usable = []
        for step, path in reversed(usable):
            run_dir = self.run_dir
            lost = [s for s in sorted(snapshot_at) if s < step and not snapshot_path(run_dir, s).is_file()]
            if lost:
                passed.append(f"{path.name}: snapshot(s) {lost} missing")
                continue
            try:  # every file read before anything is changed; a lost or cut-short one: not intact
                saved = TrainConfig.model_validate_json((path / "train_config.json").read_text())
                read = self.read(path)
            except Exception as e:
                passed.append(f"{path.name}: {type(e).__name__}")
                continue
            self.check_config(path, saved)
            self.load(path, read)
            chosen = step
            break
        for step, path in checkpoints:
            if step > chosen:  # unusable, or past a lost snapshot: recomputed from `chosen`
                shutil.rmtree(path, ignore_errors=True)
        if chosen in snapshot_at and not snapshot_path(self.run_dir, chosen).is_file():
            self.snapshot(chosen)  # the weights at that step
        return "; ".join(passed)


def _stream_seed(seed: int, purpose: str) -> int:
    """The seed of one of a run's random streams: a function of the run's seed and the purpose, so
    the streams are unrelated to each other (a generator seeded with `seed` itself draws the batches)."""
    digest = hashlib.sha256(f"capvector.trainer/{purpose}/{seed}".encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1  # 63 bits: any torch generator takes it


@contextmanager
def _drawing_from(policy: Policy, generator: torch.Generator):
    """The policy draws its loss's randomness from `generator` inside; as before it, after."""
    previous = policy.generator
    policy.set_generator(generator)
    try:
        yield
    finally:
        policy.set_generator(previous)


@torch.no_grad()
def _weighted_zero(objective: AuxObjective, features: Mapping, batch: Mapping) -> torch.Tensor:
    """An objective of weight 0: its term (0 × its loss, non-finite if that is) outside the graph. So
    no parameter gets an all-zero gradient from it (AdamW would still decay such a parameter, e.g. the
    backbone layers only an objective reads, and clipping would count the heads' zeros), and the run
    is plain SFT's, bit for bit."""
    return 0.0 * objective(features, batch)


def _cpu_state(module: nn.Module) -> dict[str, torch.Tensor]:
    return {k: v.detach().to("cpu").contiguous() for k, v in module.state_dict().items()}


def _weights_digest(module: nn.Module) -> str:
    """sha256 over the module's state (name, dtype, shape, bytes) in name order: its starting point."""
    digest = hashlib.sha256()
    for key, value in sorted(module.state_dict().items()):
        tensor = value.detach().to("cpu").contiguous()
        digest.update(f"{key}\0{tensor.dtype}\0{tuple(tensor.shape)}\0".encode())
        digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


def _param_groups(params: list[nn.Parameter], weight_decay: float) -> list[dict]:
    """Decay matrices only; biases, norms' gains and other vectors are not decayed."""
    decay = [p for p in params if p.ndim >= 2]
    rest = [p for p in params if p.ndim < 2]
    return [{"params": decay, "weight_decay": weight_decay}, {"params": rest, "weight_decay": 0.0}]


# report(done_steps, total_steps, detail): the caller decides where progress goes
# (capvector.tasks.runtime.progress)
ProgressReport = Callable[[int, int, str], None]
# on_checkpoint(step, folder): called once a resumable checkpoint is complete on disk (its loss curve
# rows up to `step` are flushed too); e.g. capvector.tasks.runtime.scratch copies it off the machine
CheckpointHook = Callable[[int, Path], None]
# after_optimizer_step(step): called after each optimizer step with its 0-based index (peft's global_step:
# AdaLoRA's update_and_allocate), gradients still in place; the loop knows nothing of what it does
StepHook = Callable[[int], None]


@runtime_checkable
class StatefulStepHook(Protocol):
    """A step hook with state of its own (as `nn.Module`'s: tensors, lists, numbers), saved in every
    checkpoint and restored on resume, so a resumed run stays exact."""

    def __call__(self, step: int) -> None: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...


def train(
    policy: Policy,
    dataset: Any,
    config: TrainConfig,
    run_dir: str | Path,
    extra_losses: Mapping[str, ExtraLoss] | None = None,
    progress: ProgressReport | None = None,
    on_checkpoint: CheckpointHook | None = None,
    after_optimizer_step: StepHook | None = None,
    snapshot_writer: SnapshotWriter | None = None,
) -> TrainResult:
    """Train ``policy`` in place on ``dataset`` (a DemoDataset: ``.tensors``, ``.meta.tasks/.instructions``).

    ``extra_losses``: name -> callable(policy) returning an already-weighted scalar, added to the loss
    and logged under its name every step (the orthogonal regularizer and LoRA-SP plug in here).
    ``on_checkpoint(step, folder)``: called after each resumable checkpoint is written (outside the
    timed loop), with ``run_dir/loss_curve.jsonl`` complete up to ``step``.
    ``after_optimizer_step(step)``: called after each optimizer step (0-based `step`, before the next
    step's zero_grad), e.g. AdaLoRA's rank allocation; a `StatefulStepHook`'s state resumes with the run.
    ``snapshot_writer(policy, path)``: writes the policy kept at each of ``snapshot_steps`` (default
    `save_policy`; an adapter run's writes its dense merge without touching the training model).
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    extra_losses = dict(extra_losses or {})
    device, execution = _set_up_torch(config)
    objective = _objective(policy, dataset, config, extra_losses)
    n, make_batch = _batcher(policy, objective, dataset, config, device)
    hooks = {"step_hook": after_optimizer_step, "snaps": snapshot_writer}
    run = _Run(policy, objective, dataset, config, run_dir, device, extra_losses, **hooks)

    curve_path = run_dir / "loss_curve.jsonl"
    passed_over = run.resume(set(config.snapshot_steps), curve_path)
    start = run.step
    _truncate_curve(curve_path, start)
    t_start = run.lap_start = time.perf_counter()
    _report_start(progress, start, config.steps, passed_over)
    with open(curve_path, "a") as file, _drawing_from(policy, run.sampling):
        curve = _Curve(file, device, progress, config.steps)
        for step in range(start, config.steps):
            lr = run.schedule(step)
            batch = make_batch(torch.randint(n, (config.batch_size,), generator=run.generator))
            total, values = run.loss(batch, curve)
            run.optimizer.zero_grad(set_to_none=True)
            total.backward()
            grad_norm = run.clip_gradients()
            run.optimizer.step()
            if after_optimizer_step is not None:
                after_optimizer_step(step)
            run.step = step + 1
            curve.add(values, grad_norm)
            run.after_step(curve, lr, on_checkpoint)
    elapsed = time.perf_counter() - t_start
    return _save_result(run, curve_path, curve.last_loss, start, elapsed, execution)


def _set_up_torch(config: TrainConfig) -> tuple[torch.device, dict[str, Any]]:
    """Threads, device and the global RNG's seed (for what draws from it: the policy draws from its
    own); returns the device and where this invocation trains (run_environment)."""
    if config.num_threads:
        torch.set_num_threads(config.num_threads)
    device = resolve_device(config.device)
    execution = run_environment(device)
    torch.manual_seed(config.seed)
    return device, execution


def _objective(
    policy: Policy, dataset: Any, config: TrainConfig, extra_losses: Mapping
) -> AuxObjective | None:
    """The auxiliary objective (None without one), once the loss names and the dataset are checked; its
    heads come from a generator of their own, so the global RNG is left as is."""
    objective = None
    if config.aux is not None:
        objective = build_objective(
            config.aux.name, policy.feature_specs(), config.aux.params, seed=config.seed
        )
    reserved = {"loss", "action"} | ({objective.name} if objective else set())
    clash = sorted(reserved & set(extra_losses))
    if clash:
        raise ValueError(f"extra loss name(s) {clash} collide with built-in loss terms {sorted(reserved)}")
    _check_dataset(dataset, policy, objective, config.batch_size)
    return objective


def _batcher(
    policy: Policy, objective: AuxObjective | None, dataset: Any, config: TrainConfig, device: torch.device
) -> tuple[int, Callable[[torch.Tensor], Mapping]]:
    """Fit the normalizer (if asked, or the policy has none) and the objective to the data; the dataset's
    size and the policy's batch maker, with the fields the objective reads."""
    tensors = dataset.tensors
    if config.fit_normalizer or (config.fit_normalizer is None and not policy.normalizer_fitted):
        policy.fit_normalizer(tensors)
    if objective is not None:
        objective.fit(tensors)
    return policy.make_batcher(
        dataset,
        device,
        fields=objective.required_fields() if objective else (),
        horizon=objective.horizon if objective else None,
    )


def _report_start(progress: ProgressReport | None, step: int, steps: int, passed_over: str) -> None:
    if progress is not None:
        how = "resumed" if step else "started"
        progress(step, steps, f"{how} (passed over {passed_over})" if passed_over else how)


def _aux_term(objective: AuxObjective, weight: float, features: Mapping, batch: Mapping) -> torch.Tensor:
    """The objective's weighted loss; of weight 0, logged but not differentiated (see _weighted_zero)."""
    if weight:
        return weight * objective(features, batch)
    return _weighted_zero(objective, features, batch)


def _total_loss(terms: dict[str, torch.Tensor], step: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The terms' sum, and the detached values of it and each term; a non-finite one stops the run,
    naming the term(s)."""
    total = torch.stack(list(terms.values())).sum()
    values = torch.stack([total.detach(), *(t.detach() for t in terms.values())])
    if not bool(torch.isfinite(values).all()):
        bad = [k for k, v in zip(["loss", *terms], values.tolist(), strict=True) if not math.isfinite(v)]
        raise FloatingPointError(f"non-finite loss at step {step}: term(s) {bad} (values {values.tolist()})")
    return total, values


class _Curve:
    """The loss curve: each step's terms and grad norm summed on the device (no sync per step), their
    means written as one row of ``loss_curve.jsonl`` per log interval."""

    def __init__(self, file, device: torch.device, progress: ProgressReport | None, steps: int):
        self.file, self.device, self.progress, self.steps = file, device, progress, steps
        self.names: list[str] = []  # loss, the policy's terms, the objective's, the extra losses, grad_norm
        self.window = torch.zeros(0, dtype=torch.float64, device=device)
        self.count = 0
        self.last_loss = float("nan")

    def name_columns(self, policy_terms: Mapping, objective: AuxObjective | None, extra: Mapping) -> None:
        if not self.names:
            self.names = _term_names(policy_terms, objective, extra)
            self.window = torch.zeros(len(self.names), dtype=torch.float64, device=self.device)

    def add(self, values: torch.Tensor, grad_norm: torch.Tensor) -> None:
        self.window += torch.cat([values, grad_norm.detach().reshape(1)]).double()
        self.count += 1

    def write_row(self, step: int, lr: float, seconds: float) -> None:
        """The means since the last row; reported to ``progress`` with the mean loss."""
        means = (self.window / self.count).tolist()
        row = {"step": step, "lr": lr, "time": round(seconds, 4)}
        row.update(dict(zip(self.names, means, strict=True)))
        self.file.write(json.dumps(row) + "\n")
        self.file.flush()
        self.last_loss = means[0]
        self.window.zero_()
        self.count = 0
        if self.progress is not None:
            self.progress(step, self.steps, f"loss {self.last_loss:.4f}")

    def sync(self) -> None:
        """On disk before a checkpoint: a resume finds the rows up to it."""
        self.file.flush()
        os.fsync(self.file.fileno())


def _save_result(
    run: _Run, curve_path: Path, last_loss: float, start: int, elapsed: float, execution: dict[str, Any]
) -> TrainResult:
    """Write the final policy, the aux heads (with an objective) and ``result.json``; return the result."""
    config, run_dir = run.config, run.run_dir
    done_steps = config.steps - start
    meta = {"capvector.train_config": config.model_dump_json(), "capvector.steps": str(config.steps)}
    weights = save_policy(run.policy, run_dir / "policy.safetensors", metadata=meta)
    aux_path = None
    if run.objective is not None:
        aux_path = run_dir / "aux_heads.safetensors"
        save_tensors_atomic(
            _cpu_state(run.objective), aux_path, {"capvector.aux": config.aux.model_dump_json()}
        )
    if math.isnan(last_loss):  # no row this invocation (resumed at the end): the curve's last
        last_loss = _last_logged_loss(curve_path)
    result = TrainResult(
        weights_path=weights,
        aux_weights_path=aux_path,
        loss_curve_path=curve_path,
        steps=config.steps,
        resumed_from_step=start,
        train_seconds=run.train_seconds,
        steps_per_s=done_steps / elapsed if done_steps and elapsed > 0 else 0.0,
        samples_per_s=done_steps * config.batch_size / elapsed if done_steps and elapsed > 0 else 0.0,
        final_loss=last_loss,
        snapshots={s: snapshot_path(run_dir, s) for s in sorted(config.snapshot_steps)},
        execution=execution,
    )
    (run_dir / "result.json").write_text(result.model_dump_json(indent=1))
    return result


def snapshot_path(run_dir: Path, step: int) -> Path:
    return run_dir / "snapshots" / f"step_{step:08d}.safetensors"


def _term_names(policy_terms: Mapping, objective: AuxObjective | None, extra: Mapping) -> list[str]:
    """Curve columns; a policy term may not share a name with the objective or an extra loss."""
    others = ([objective.name] if objective else []) + list(extra)
    clash = sorted(({"loss", "grad_norm"} | set(others)) & set(policy_terms))
    if clash:
        raise ValueError(f"policy loss term(s) {clash} collide with the objective's or extra losses' names")
    return ["loss", *policy_terms, *others, "grad_norm"]


def _truncate_curve(path: Path, step: int) -> None:
    """Drop rows logged after the checkpoint we resume from (a killed run may have logged past it)."""
    if not path.exists():
        return
    keep = []
    for line in path.read_text().splitlines():
        try:
            row = json.loads(line)
        except json.JSONDecodeError:  # a line cut short by the kill
            continue
        if row["step"] <= step:
            keep.append(line)
    write_atomic(path, "".join(line + "\n" for line in keep))


def _last_logged_loss(path: Path) -> float:
    lines = [line for line in path.read_text().splitlines() if line.strip()]
    return json.loads(lines[-1])["loss"] if lines else float("nan")
