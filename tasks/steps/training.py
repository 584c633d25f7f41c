"""Step: train a policy (pretraining, standard or auxiliary SFT, downstream fine-tuning) into a checkpoint.

One step covers every training stage of the recipe; what differs is the config (aux objective,
adapter, orthogonal regularizer) and the inputs (`data`, optional `init` checkpoint, optional
`vector` γ for the regularizer). The checkpoint artifact holds dense weights only (LoRA runs are
merged), so vectors can be taken from any of them; its record keeps the loss curve and run summary,
and a LoRA/LoRA-SP/AdaLoRA adapter is a separate artifact, its parent with role `adapter`. The checkpoint
is registered last: it is the step's commit point.

Where it trained is provenance, not part of the cache key (capvector.core.training.execution): the records of
the checkpoint, its snapshots and its adapter hold `execution`, what the training invocation that
finished the run used (capvector.core.training.device.run_environment): the resolved device (`cpu`, `cuda:0`,
never `auto`), its name, torch's CPU thread count, the torch build and whether CUDA was available. A
run resumed from another invocation's checkpoint says so in `summary.resumed_from_step`; that
invocation may have run on another machine (capvector.tasks.runtime.scratch: resume checkpoints are copied to
a shared scratch URL, by default `<home>/scratch` for a remote home, and fetched by the next run).
"""

from __future__ import annotations

import functools
import json
import shutil
from pathlib import Path
from typing import Any, ClassVar, Literal

import torch
from pydantic import BaseModel, ConfigDict, Field, model_validator

from capvector.core.adapters import lora
from capvector.core.adapters.adalora import AdaLoraConfig
from capvector.core.adapters.lora import LoraConfig
from capvector.core.adapters.lora_sp import LoraSPConfig
from capvector.core.policies.base import AnyPolicyConfig, Policy, build_policy, load_policy, save_policy
from capvector.core.simulation.demos import DemoDataset
from capvector.core.training.orthogonal import OrthogonalRegularizer
from capvector.core.training.trainer import StepHook, TrainConfig, TrainResult, train
from capvector.tasks.adapters import ADAPTERS, snapshot_adapter_files
from capvector.tasks.runtime.caching import selected_by
from capvector.tasks.runtime.progress import progress_printer
from capvector.tasks.runtime.step_kinds import StepCall, StepKind, step_task
from capvector.tasks.runtime.workspace import Workspace, provenance

CALIBRATION_BATCHES = 8


PAPER_LAMBDA = 1e-4  # the paper's λ, tuned on a 7B model where Σ|γ ⊙ Δ| is far larger than here
LAMBDA_FORMS = ("lambda_absolute", "lambda_relative")


class OrthogonalSettings(BaseModel):
    """λ·Σ|γ ⊙ Δ'|, with λ in one of two forms, each with its own name: `lambda_absolute` (λ itself, the
    paper's form) or `lambda_relative` (λ as a multiple of ‖∇ action loss‖/‖γ‖ at θ_meta, which carries
    across models). `lora_mode` for adapters: `lora_exact` (B·A materialised) or `lora_a` (A only)."""

    model_config = ConfigDict(extra="forbid")
    one_of: ClassVar[tuple[str, ...]] = LAMBDA_FORMS  # an override of one clears the other
    renamed: ClassVar[dict[str, str]] = dict.fromkeys(
        ("weight", "scale"),
        "set lambda_absolute (λ itself) or lambda_relative (λ as a multiple of ‖∇ action loss‖/‖γ‖)",
    )
    lambda_absolute: float | None = Field(
        None,
        ge=0,
        allow_inf_nan=False,
        description=f"λ itself (the paper's form; null with lambda_relative set, else {PAPER_LAMBDA:g}, the "
        "paper's best on a 7B model); larger: downstream updates kept further off γ, 0: no penalty",
    )
    lambda_relative: float | None = Field(
        None,
        ge=0,
        allow_inf_nan=False,
        description="λ as a multiple of ‖∇ action loss‖/‖γ‖ measured at θ_meta before training: 1 gives "
        "the penalty a gradient as large as the action loss's on any model (full fine-tuning only); "
        "set this or lambda_absolute, not both",
    )
    lora_mode: Literal["lora_exact", "lora_a"] = Field(
        "lora_exact",
        description="adapter arms: `lora_exact` penalises each adapter's dense update B·A against γ; "
        "`lora_a` the cheaper projection of γ on A only",
    )
    include: list[str] | None = Field(
        None,
        description="γ tensors the penalty covers, by name (module_patterns syntax); null: all of them",
    )
    exclude: list[str] | None = Field(
        None, description="γ tensors left out of the penalty (module_patterns syntax); null: none"
    )


    @model_validator(mode="before")
    @classmethod
    def _one_form_of_lambda(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        old = sorted(set(cls.renamed) & set(data))
        if old:
            raise ValueError(f"orthogonal.{old[0]} was renamed: {cls.renamed[old[0]]}")
        given = [f for f in LAMBDA_FORMS if data.get(f) is not None]
        if len(given) == 2:
            raise ValueError(
                "orthogonal.lambda_absolute and orthogonal.lambda_relative are both set: λ takes one form"
            )
        if not given:
            data = {**data, "lambda_absolute": PAPER_LAMBDA}
        return data

    @property
    def lam(self) -> dict[str, float]:
        """The one λ set, under its form's name, e.g. {"lambda_relative": 0.1}."""
        return {f: getattr(self, f) for f in LAMBDA_FORMS if getattr(self, f) is not None}

    def with_lambda(self, lam: dict[str, float]) -> OrthogonalSettings:
        """These settings with λ replaced by `lam` (one form, as `lam` gives it)."""
        return OrthogonalSettings.model_validate({**self.model_dump(exclude=set(LAMBDA_FORMS)), **lam})


class TrainStepConfig(BaseModel):
    """Everything that decides a trained checkpoint besides its input artifacts."""

    model_config = ConfigDict(extra="forbid")
    policy: AnyPolicyConfig | None = None  # only for training from scratch (no `init` input)
    train: TrainConfig
    adapter: Literal[tuple(ADAPTERS)] = "full"  # type: ignore[valid-type]  # capvector.tasks.adapters: the registry
    lora: LoraConfig | None = None
    lora_sp: LoraSPConfig | None = None
    adalora: AdaLoraConfig | None = None
    orthogonal: OrthogonalSettings | None = None

    @model_validator(mode="after")
    def _adapter_config_present(self) -> TrainStepConfig:
        form = ADAPTERS[self.adapter]
        if form.section and form.settings(self) is None:
            raise ValueError(f"adapter {self.adapter!r} needs a `{self.adapter}` config")
        form.check(self)
        return self


def _initial_policy(workspace: Workspace, cfg: TrainStepConfig, init_id: str | None) -> Policy:
    """θ from `init`, or a fresh model whose initialisation depends on the training seed alone."""
    torch.manual_seed(cfg.train.seed)  # also seeds adapter initialisation, which follows
    if init_id is None:
        if cfg.policy is None:
            raise ValueError("training from scratch (no `init` checkpoint) needs a `policy` config")
        return build_policy(cfg.policy, device=cfg.train.device)
    return load_policy(workspace.path(init_id), device=cfg.train.device)


def _orthogonal(
    workspace: Workspace, model: Policy, cfg: TrainStepConfig, inputs: dict[str, str]
) -> OrthogonalRegularizer | None:
    if cfg.orthogonal is None:
        return None
    if "vector" not in inputs or "init" not in inputs:
        raise ValueError("the orthogonal regularizer needs inputs `vector` (γ) and `init` (θ_meta)")
    settings = cfg.orthogonal
    mode = ADAPTERS[cfg.adapter].orthogonal_mode(settings.lora_mode)
    if settings.lambda_relative is not None and mode != "dense":
        raise ValueError("orthogonal.lambda_relative needs full fine-tuning (adapter 'full')")
    return OrthogonalRegularizer(
        model,
        workspace.path(inputs["vector"]),
        workspace.path(inputs["init"]) if mode == "dense" else None,
        lambda_absolute=settings.lambda_absolute or 0.0,  # a relative λ is set once measured
        include=settings.include,
        exclude=settings.exclude,
        mode=mode,
    )


def action_gradient_scale(
    model: Policy, dataset: DemoDataset, regularizer: OrthogonalRegularizer, seed: int, batch_size: int
) -> float:
    """‖∇ action loss‖ / ‖γ‖ over the regularized tensors, at the model as training starts.

    The regularizer's gradient is λ·γ ⊙ sign(θ − θ_meta), of norm λ·‖γ‖ once every Δ is non-zero; the
    action loss's gradient norm is averaged over a few training batches (a fixed generator: no RNG state
    of the run is used).
    """
    batches = _calibration_batches(model, dataset, seed, batch_size)
    losses = (torch.stack(list(model.compute_loss(batch).terms.values())).sum() for batch in batches)
    return regularizer.gradient_ratio(model, losses)


def _calibration_batches(
    model: Policy, dataset: DemoDataset, seed: int, batch_size: int = 256
) -> list[dict[str, torch.Tensor]]:
    """Batches from the training data (LoRA-SP's dense merge, the orthogonal loss's scale)."""
    n, make_batch = model.make_batcher(dataset, model.device)
    generator = torch.Generator().manual_seed(seed)
    return [
        make_batch(torch.randint(0, n, (min(batch_size, n),), generator=generator))
        for _ in range(CALIBRATION_BATCHES)
    ]


def _train_checkpoint(call: StepCall) -> str:
    """Train, then register the checkpoint; the run folder is kept until the checkpoint is committed."""
    workspace, step, inputs, cfg, key = call.workspace, call.step, call.inputs, call.config, call.key
    form = ADAPTERS[cfg.adapter]
    dataset = DemoDataset.load(workspace.path(inputs["data"]))
    model = _initial_policy(workspace, cfg, inputs.get("init"))
    form.apply(model, cfg)
    extra, lam = _orthogonal_loss(workspace, model, dataset, cfg, inputs)
    extra |= form.extra_losses()
    trainable = lora.trainable_parameter_count(model)
    hook = form.after_optimizer_step(model)
    result = _train_resumable(workspace, step, key, model, dataset, cfg, extra, hook)
    summary = {
        "step": step,
        "steps": result.steps,
        "steps_per_s": result.steps_per_s,
        "samples_per_s": result.samples_per_s,
        "final_loss": result.final_loss,
        "resumed_from_step": result.resumed_from_step,
        "trainable_parameters": trainable,
        "adapter": cfg.adapter,
        **lam,
    }
    checkpoint_id = _register_checkpoint(workspace, step, inputs, cfg, key, model, dataset, result, summary)
    workspace.finish_run_dir(key)
    return checkpoint_id


def _orthogonal_loss(
    workspace: Workspace, model: Policy, dataset: DemoDataset, cfg: TrainStepConfig, inputs: dict[str, str]
) -> tuple[dict[str, Any], dict[str, float]]:
    """The orthogonal regularizer as an extra loss (none without `orthogonal`), and the λ it ended up
    with for the run summary."""
    regularizer = _orthogonal(workspace, model, cfg, inputs)
    if regularizer is None:
        return {}, {}
    lam = cfg.orthogonal.lam
    if cfg.orthogonal.lambda_relative is not None:
        ratio = action_gradient_scale(model, dataset, regularizer, cfg.train.seed, cfg.train.batch_size)
        regularizer.lambda_absolute = cfg.orthogonal.lambda_relative * ratio
        lam["gradient_ratio"] = ratio  # ‖∇ action loss‖/‖γ‖ at the start: λ = lambda_relative × this
    lam["lambda_absolute"] = regularizer.lambda_absolute
    return {"orthogonal": regularizer}, lam


def _train_resumable(
    workspace: Workspace,
    step: str,
    key: str,
    model: Policy,
    dataset: DemoDataset,
    cfg: TrainStepConfig,
    extra: dict[str, Any],
    after_optimizer_step: StepHook | None = None,
) -> TrainResult:
    """`train` in the key's run folder; with a checkpoint mirror (capvector.tasks.runtime.scratch) it
    resumes from another machine's checkpoint and copies ours. `after_optimizer_step`: the adapter's hook
    (AdaLoRA's rank allocation), or None."""
    run_dir = workspace.run_dir(key)
    mirror = workspace.checkpoint_mirror(key)
    calibration = functools.partial(_calibration_batches, model, dataset, cfg.train.seed)
    writer = functools.partial(ADAPTERS[cfg.adapter].snapshot, calibration=calibration)
    on_checkpoint = None
    if mirror is not None:
        mirror.restore(run_dir)
        on_checkpoint = functools.partial(mirror.save, run_dir=run_dir)
    return train(
        model,
        dataset,
        cfg.train,
        run_dir,
        extra_losses=extra,
        progress=progress_printer(step, "steps"),
        on_checkpoint=on_checkpoint,
        after_optimizer_step=after_optimizer_step,
        snapshot_writer=writer,
    )


def _register_checkpoint(
    workspace: Workspace,
    step: str,
    inputs: dict[str, str],
    cfg: TrainStepConfig,
    key: str,
    model: Policy,
    dataset: DemoDataset,
    result: TrainResult,
    summary: dict[str, Any],
) -> str:
    """Register the adapter and snapshots, then the checkpoint that names them (the commit point)."""
    form = ADAPTERS[cfg.adapter]
    with workspace.scratch() as tmp:
        calibration = lambda: _calibration_batches(model, dataset, cfg.train.seed)  # noqa: E731
        adapter_dir = form.finish(model, tmp / "adapter", calibration, summary)
        weights = save_policy(model, tmp / "model.safetensors", {"capvector.step": step})
        parents = _input_parents(inputs)
        meta = provenance()
        snapshots = _register_snapshots(workspace, step, cfg, key, result, parents, meta)
        if adapter_dir is not None:
            adapter = workspace.api.register_dir(
                adapter_dir,
                kind="adapter",
                name=f"{step} adapter",
                config={"adapter": cfg.adapter, "summary": summary, "execution": result.execution},
                parents=parents,
                **meta,
            )
            parents.append((adapter.id, "adapter"))
        record_config = {
            "train_step": cfg.model_dump(mode="json"),
            "cache_key": key,
            "summary": summary,
            "execution": result.execution,
            "curve": _curve_rows(result.loss_curve_path),
            "snapshots": snapshots,
        }
        parents += [(i, "snapshot", {"budget": int(b)}) for b, i in snapshots.items()]
        checkpoint = workspace.api.register_file(
            weights, kind="checkpoint", name=step, config=record_config, parents=parents, **meta
        )
    return checkpoint.id


def _input_parents(inputs: dict[str, str]) -> list[tuple[Any, ...]]:
    """The checkpoint's lineage from its inputs: data, θ it started from, γ it was regularized by."""
    parents: list[tuple[Any, ...]] = [(inputs["data"], "data")]
    if "init" in inputs:
        parents.append((inputs["init"], "init"))
    if "vector" in inputs:
        parents.append((inputs["vector"], "regularized_by"))
    return parents + selected_by(inputs)


def _register_snapshots(
    workspace: Workspace,
    step: str,
    cfg: TrainStepConfig,
    key: str,
    result: TrainResult,
    parents: list[tuple[Any, ...]],
    meta: dict[str, Any],
) -> dict[str, str]:
    """Budget -> id of each checkpoint kept on the way, registered before the final one, which names them;
    a snapshot with adapter files beside it (LoRA-SP: evaluated as `init` + adapter) has its own adapter
    artifact as its parent `adapter`."""
    snapshots = {}
    for budget, path in result.snapshots.items():
        own = _snapshot_adapter(workspace, step, cfg, budget, path, parents, meta)
        snapshot = workspace.api.register_file(
            path,
            kind="checkpoint",
            name=f"{step} @ {budget} steps",
            config={
                "train_step": cfg.model_dump(mode="json"),
                "budget": budget,
                "of_run": key,
                "execution": result.execution,
            },
            parents=parents + own,
            **meta,
        )
        snapshots[str(budget)] = snapshot.id
    return snapshots


def _snapshot_adapter(
    workspace: Workspace,
    step: str,
    cfg: TrainStepConfig,
    budget: int,
    path: Path,
    parents: list[tuple[Any, ...]],
    meta: dict[str, Any],
) -> list[tuple[Any, ...]]:
    """The adapter a snapshot was kept with (`tasks.adapters.snapshot_adapter_files`), registered; [(id,
    "adapter")], or [] when it has none."""
    files = snapshot_adapter_files(path)
    if not files:
        return []
    with workspace.scratch() as tmp:
        folder = tmp / "adapter"
        folder.mkdir()
        for f in files:
            shutil.copyfile(f, folder / f.name.removeprefix(f"{path.stem}."))
        adapter = workspace.api.register_dir(
            folder,
            kind="adapter",
            name=f"{step} @ {budget} steps adapter",
            config={"adapter": cfg.adapter, "budget": budget},
            parents=parents,
            **meta,
        )
    return [(adapter.id, "adapter")]


def snapshots_of(workspace: Workspace, checkpoint_id: str) -> dict[int, str]:
    """Budget (steps) -> id of the checkpoint a training run kept at that budget; the final one included."""
    record = workspace.api.get(checkpoint_id)
    found = {int(b): i for b, i in (record.config or {}).get("snapshots", {}).items()}
    found[record.config["train_step"]["train"]["steps"]] = record.id
    return dict(sorted(found.items()))


def _curve_rows(path: Path) -> list[dict[str, Any]]:
    """The loss curve (one JSON row per logged step), kept in the checkpoint's record."""
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


TRAIN = StepKind("train", TrainStepConfig, ("data",), _train_checkpoint, key_on_model=True)
run_train = TRAIN.run
train_task = step_task(TRAIN)
