"""Expert demonstrations: parallel collection with Meta-World's scripted experts, and `DemoDataset`,
stored as `data.safetensors` + `meta.json` (no pickle) with normalization stats and a content hash.

Seeds (goal variations, see envs.py) come from disjoint ranges so that no evaluation goal was ever
seen in training: demos use [TRAIN_SEED_BASE, TRAIN_SEED_BASE + TRAIN_SEED_SPAN), model selection
uses VALIDATION_SEED_BASE + i, final evaluation uses EVAL_SEED_BASE + i.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import math
import multiprocessing
import os
import shutil
import uuid
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from multiprocessing import util as mp_util
from pathlib import Path
from typing import Annotated, Any

import mujoco
import numpy as np
import torch
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializerFunctionWrapHandler,
    ValidationError,
    field_validator,
    model_serializer,
    model_validator,
)
from safetensors.torch import load_file, save_file

from capvector.core.simulation.envs import (
    GOAL_SAMPLING,
    EnvConfig,
    MetaWorldEnv,
    ObsMode,
    expert_action,
)
from capvector.core.simulation.metaworld_tasks import INSTRUCTIONS, validate_task_names
from capvector.core.training.execution import ExecutionOnly
from capvector.durable import fsync_files

TRAIN_SEED_BASE = 0
TRAIN_SEED_SPAN = 10_000
VALIDATION_SEED_BASE = 50_000
EVAL_SEED_BASE = 100_000

SUCCESS_TAIL = 10  # steps kept after the first success: shows the settled goal state, keeps data small
UNIT_EPISODES = 5  # successful episodes per work unit: the grain of parallelism
UNIT_SEEDS = 50  # seeds reserved per work unit; seed = base + offset + unit * UNIT_SEEDS + attempt
STD_FLOOR = 1e-2  # constant dims (padding, fixed heights) must not blow up when normalized
FLOAT_KEYS = ("state", "proprio", "privileged", "action")
REQUIRED_FIELDS = ("state", "proprio", "action", "episode", "step", "task")
DATA_FILE, META_FILE = "data.safetensors", "meta.json"

Progress = Callable[[int, int], None]


class DemoConfig(BaseModel):
    """What to collect. `workers` changes speed only, never the data or its hash.

    `patch_xyz` (pixels mode) also records, per step, the world point each cell of a `patch_grid` ×
    `patch_grid` split of the image sees (field `patch_xyz`, float32 (N, patch_grid², 3), NaN where a
    cell sees no geometry; from a depth render, see depth_targets.py): the `spatial_depth` objective's
    targets. `patch_grid` must be the policy's token grid, image_size / 2**len(stem_channels). Both
    are left out of the config's dump while `patch_xyz` is off, so other configs dump as before.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    tasks: list[str]
    episodes_per_task: int = Field(25, ge=1)
    obs_mode: ObsMode = "state"
    camera: str = "corner2"
    image_size: int = Field(64, ge=16, le=256)
    horizon: int = Field(500, ge=1, le=500)
    seed_offset: int = Field(0, ge=0)
    workers: Annotated[int, ExecutionOnly("units merge in (task, unit) order: the same data")] = Field(
        2, ge=1
    )
    patch_xyz: bool = False
    patch_grid: int = Field(4, ge=1, description="patches per image side for patch_xyz")

    @field_validator("tasks")
    @classmethod
    def _known_tasks(cls, tasks: list[str]) -> list[str]:
        return validate_task_names(tasks)

    @model_validator(mode="after")
    def _seeds_in_training_range(self) -> DemoConfig:
        last = self.seed_offset + self.n_units * UNIT_SEEDS
        if last > TRAIN_SEED_SPAN:
            raise ValueError(
                f"seed_offset {self.seed_offset} with {self.episodes_per_task} episodes per task needs "
                f"training seeds up to {TRAIN_SEED_BASE + last}, beyond the training range "
                f"[{TRAIN_SEED_BASE}, {TRAIN_SEED_BASE + TRAIN_SEED_SPAN})"
            )
        self.env_config(self.tasks[0])  # validates the camera name and the patch grid
        return self

    @model_serializer(mode="wrap")
    def _omit_patch_fields_when_off(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        data = handler(self)
        if not self.patch_xyz:
            data.pop("patch_xyz", None)
            data.pop("patch_grid", None)
        return data

    def env_config(self, task: str) -> EnvConfig:
        return EnvConfig(
            task=task,
            obs_mode=self.obs_mode,
            camera=self.camera,
            image_size=self.image_size,
            horizon=self.horizon,
            patch_grid=self.patch_grid if self.patch_xyz else None,
        )

    @property
    def n_units(self) -> int:
        return math.ceil(self.episodes_per_task / UNIT_EPISODES)


class DatasetMeta(BaseModel):
    """Everything needed to interpret, reproduce and identify a dataset (stored as meta.json)."""

    model_config = ConfigDict(extra="forbid")

    format_version: int = 1
    tasks: list[str]
    instructions: list[str]
    obs_mode: ObsMode
    camera: str
    image_size: int
    horizon: int
    episodes_per_task: int
    seed_offset: int
    success_tail: int = SUCCESS_TAIL
    goal_sampling: str = GOAL_SAMPLING
    seeds: dict[str, list[int]]  # per task, the seed of each kept episode, in episode order
    failures: dict[str, int]  # per task, expert episodes without success within the horizon
    n_episodes: int
    n_steps: int
    normalization: dict[str, dict[str, list[float]]] = {}  # float key -> {"mean": [...], "std": [...]}
    versions: dict[str, str] = {}
    content_hash: str = ""


class DemoDataset:
    """Demonstration steps as flat tensors (see docs/architecture.md) plus `DatasetMeta`."""

    def __init__(self, tensors: dict[str, torch.Tensor], meta: DatasetMeta):
        _check_tensors(tensors, meta)
        self.tensors = tensors
        self.meta = meta

    @classmethod
    def create(cls, tensors: dict[str, torch.Tensor], meta: DatasetMeta) -> DemoDataset:
        """A dataset whose normalization stats and content hash are computed from `tensors`."""
        dataset = cls(tensors, meta.model_copy(update={"normalization": _normalization(tensors)}))
        dataset.meta.content_hash = dataset.compute_hash()
        return dataset

    @property
    def content_hash(self) -> str:
        return self.meta.content_hash

    def __len__(self) -> int:
        return int(self.tensors["action"].shape[0])

    def compute_hash(self) -> str:
        """sha256 over each tensor (name, dtype, shape, bytes) in sorted key order, then the meta."""
        digest = hashlib.sha256()
        for key in sorted(self.tensors):
            tensor = self.tensors[key].contiguous()
            digest.update(f"{key}\0{tensor.dtype}\0{tuple(tensor.shape)}\0".encode())
            digest.update(tensor.numpy().tobytes())
        digest.update(_canonical_json(self.meta.model_dump(exclude={"content_hash"})).encode())
        return digest.hexdigest()

    def normalization_stats(self) -> dict[str, dict[str, torch.Tensor]]:
        """Per float key, {"mean", "std"} float32 tensors; std is floored at STD_FLOOR."""
        return {
            key: {name: torch.tensor(values, dtype=torch.float32) for name, values in stats.items()}
            for key, stats in self.meta.normalization.items()
        }

    def require_fields(self, names: Iterable[str], purpose: str) -> None:
        """Raise ValueError naming the fields `purpose` needs that this dataset lacks."""
        missing = [name for name in names if name not in self.tensors]
        if missing:
            raise ValueError(
                f"{purpose} needs dataset field(s) {missing}, but this dataset "
                f"({self.content_hash[:12] or 'unsaved'}) has only {sorted(self.tensors)}"
            )

    def save(self, directory: str | os.PathLike, overwrite: bool = False) -> Path:
        """Write data.safetensors + meta.json into a temporary sibling directory, fsync, then rename."""
        target = Path(directory)
        if target.exists() and not overwrite:
            raise FileExistsError(f"{target} already exists; pass overwrite=True to replace it")
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.parent / f".{target.name}.tmp-{uuid.uuid4().hex[:8]}"
        tmp.mkdir()
        try:
            tensors = {k: v.contiguous() for k, v in self.tensors.items()}
            save_file(tensors, str(tmp / DATA_FILE), metadata={"content_hash": self.content_hash})
            (tmp / META_FILE).write_text(self.meta.model_dump_json(indent=1))
            fsync_files(tmp)
            _replace_directory(tmp, target)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        return target

    @classmethod
    def load(cls, directory: str | os.PathLike) -> DemoDataset:
        """Load and verify a saved dataset; errors name the missing file, field or hash mismatch."""
        directory = Path(directory)
        for name in (DATA_FILE, META_FILE):
            if not (directory / name).is_file():
                raise FileNotFoundError(f"{directory} is not a demo dataset: {name} is missing")
        try:
            meta = DatasetMeta.model_validate_json((directory / META_FILE).read_text())
        except ValidationError as err:
            raise ValueError(f"{directory / META_FILE} is not valid dataset metadata: {err}") from err
        dataset = cls(load_file(str(directory / DATA_FILE)), meta)
        actual = dataset.compute_hash()
        if actual != meta.content_hash:
            raise ValueError(
                f"{directory}: content hash mismatch (meta.json says {meta.content_hash[:12]}, "
                f"data gives {actual[:12]}); the files were modified or are from different datasets"
            )
        return dataset


def _check_tensors(tensors: dict[str, torch.Tensor], meta: DatasetMeta) -> None:
    required = REQUIRED_FIELDS + (("image",) if meta.obs_mode == "pixels" else ())
    missing = [name for name in required if name not in tensors]
    if missing:
        raise ValueError(f"demo dataset lacks required field(s) {missing}; it has {sorted(tensors)}")
    if "patch_xyz" in tensors:
        patch = tensors["patch_xyz"]
        n_patches = patch.shape[1] if patch.ndim == 3 else 0
        if patch.dtype != torch.float32 or patch.ndim != 3 or patch.shape[2] != 3 or not n_patches:
            raise ValueError(
                f"patch_xyz must be float32 (N, patches, 3), got {patch.dtype} {tuple(patch.shape)}"
            )
        if math.isqrt(n_patches) ** 2 != n_patches:
            raise ValueError(f"patch_xyz has {n_patches} patches per image, not a square grid")
    lengths = {key: int(t.shape[0]) for key, t in tensors.items()}
    if len(set(lengths.values())) != 1:
        raise ValueError(f"demo dataset fields have different numbers of steps: {lengths}")


def _normalization(tensors: dict[str, torch.Tensor]) -> dict[str, dict[str, list[float]]]:
    stats = {}
    for key in FLOAT_KEYS:
        if key in tensors:
            values = tensors[key].double()
            std = values.std(dim=0, unbiased=False).clamp_min(STD_FLOOR)
            stats[key] = {"mean": values.mean(dim=0).tolist(), "std": std.tolist()}
    return stats


def _canonical_json(value: object) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=True)


def _replace_directory(new: Path, target: Path) -> None:
    """Rename `new` to `target`; an existing `target` is moved aside first and removed afterwards."""
    if not target.exists():
        os.rename(new, target)
        return
    old = target.parent / f".{target.name}.old-{uuid.uuid4().hex[:8]}"
    os.rename(target, old)
    os.rename(new, target)
    shutil.rmtree(old, ignore_errors=True)


def library_versions() -> dict[str, str]:
    """Versions of the libraries that determine simulated data and scores."""
    return {
        "metaworld": importlib.metadata.version("metaworld"),
        "mujoco": mujoco.__version__,
        "numpy": np.__version__,
        "torch": torch.__version__,
    }


# ---------------------------------------------------------------- collection


@dataclass(frozen=True)
class _Unit:
    """A slice of one task's collection: up to `needed` successes from its own block of seeds."""

    task_index: int
    unit_index: int
    env: EnvConfig
    first_seed: int
    needed: int


@dataclass
class _UnitResult:
    unit: _Unit
    episodes: list[tuple[int, dict[str, np.ndarray]]]  # (seed, per-step arrays)
    failures: int


def _units(config: DemoConfig) -> list[_Unit]:
    units = []
    for task_index, task in enumerate(config.tasks):
        env = config.env_config(task)
        for u in range(config.n_units):
            needed = min(UNIT_EPISODES, config.episodes_per_task - u * UNIT_EPISODES)
            first_seed = TRAIN_SEED_BASE + config.seed_offset + u * UNIT_SEEDS
            units.append(_Unit(task_index, u, env, first_seed, needed))
    return units


def expert_episode(env: MetaWorldEnv, seed: int) -> dict[str, np.ndarray] | None:
    """Run the scripted expert from `seed`; the steps up to SUCCESS_TAIL after success, else None."""
    obs = env.reset(seed)
    steps: list[dict[str, np.ndarray]] = []
    success_at = None
    while env.steps < env.config.horizon and (success_at is None or env.steps < success_at + SUCCESS_TAIL):
        action = expert_action(env.task, obs["state"])
        steps.append({**obs, "action": action})
        obs, _, success, _ = env.step(action)
        if success and success_at is None:
            success_at = env.steps
    if success_at is None:
        return None
    return {key: np.stack([step[key] for step in steps]) for key in steps[0]}


_WORKER_ENVS: dict[EnvConfig, MetaWorldEnv] = {}


def _worker_env(config: EnvConfig) -> MetaWorldEnv:
    """Envs are reused across units in a process: construction costs as much as ~200 steps."""
    if config not in _WORKER_ENVS:
        _WORKER_ENVS[config] = MetaWorldEnv(config)
    return _WORKER_ENVS[config]


def _close_worker_envs() -> None:
    while _WORKER_ENVS:
        _WORKER_ENVS.popitem()[1].close()


def _init_worker() -> None:
    mp_util.Finalize(None, _close_worker_envs, exitpriority=10)


def _run_unit(unit: _Unit) -> _UnitResult:
    env = _worker_env(unit.env)
    episodes, failures = [], 0
    for seed in range(unit.first_seed, unit.first_seed + UNIT_SEEDS):
        if len(episodes) == unit.needed:
            break
        episode = expert_episode(env, seed)
        if episode is None:
            failures += 1
        else:
            episodes.append((seed, episode))
    return _UnitResult(unit, episodes, failures)


def _run_units(units: list[_Unit], workers: int, on_result: Callable[[_UnitResult], None]) -> None:
    if workers == 1:
        try:
            for unit in units:
                on_result(_run_unit(unit))
        finally:
            _close_worker_envs()
        return
    context = multiprocessing.get_context("spawn")  # fork would copy GL/EGL state; spawn is safe
    pool = context.Pool(min(workers, len(units)), initializer=_init_worker)
    try:
        for result in pool.imap_unordered(_run_unit, units):
            on_result(result)
        pool.close()
    except BaseException:
        pool.terminate()
        raise
    finally:
        pool.join()


def collect_demos(config: DemoConfig, progress: Progress | None = None) -> DemoDataset:
    """Collect `episodes_per_task` successful expert episodes per task in `config.workers` processes.

    The result depends only on the config minus `workers`: units are merged in (task, unit) order.
    A task whose expert fails too often keeps the episodes it got; shortfalls show in meta.
    """
    units = _units(config)
    total = len(config.tasks) * config.episodes_per_task
    results: list[_UnitResult] = []

    def on_result(result: _UnitResult) -> None:
        results.append(result)
        if progress is not None:
            progress(sum(len(r.episodes) for r in results), total)

    _run_units(units, config.workers, on_result)
    results.sort(key=lambda r: (r.unit.task_index, r.unit.unit_index))
    if not any(r.episodes for r in results):
        raise RuntimeError(
            f"the scripted expert succeeded in no episode within horizon {config.horizon} on {config.tasks}"
        )
    return _assemble(config, results)


def _assemble(config: DemoConfig, results: list[_UnitResult]) -> DemoDataset:
    columns: dict[str, list[np.ndarray]] = {}
    seeds: dict[str, list[int]] = {task: [] for task in config.tasks}
    failures = dict.fromkeys(config.tasks, 0)
    n_episodes = 0
    for result in results:
        task = config.tasks[result.unit.task_index]
        failures[task] += result.failures
        for seed, episode in result.episodes:
            length = len(episode["action"])
            for key, values in episode.items():
                columns.setdefault(key, []).append(values)
            columns.setdefault("episode", []).append(np.full(length, n_episodes, dtype=np.int64))
            columns.setdefault("step", []).append(np.arange(length, dtype=np.int64))
            columns.setdefault("task", []).append(np.full(length, result.unit.task_index, dtype=np.int64))
            seeds[task].append(seed)
            n_episodes += 1
    tensors = {key: torch.from_numpy(np.concatenate(parts)) for key, parts in columns.items()}
    meta = DatasetMeta(
        tasks=config.tasks,
        instructions=[INSTRUCTIONS[task] for task in config.tasks],
        obs_mode=config.obs_mode,
        camera=config.camera,
        image_size=config.image_size,
        horizon=config.horizon,
        episodes_per_task=config.episodes_per_task,
        seed_offset=config.seed_offset,
        seeds=seeds,
        failures=failures,
        n_episodes=n_episodes,
        n_steps=int(tensors["action"].shape[0]),
        versions=library_versions(),
    )
    return DemoDataset.create(tensors, meta)
