"""Batched policy evaluation on Meta-World v3 with a protocol fingerprint on every result.

All episodes of a batch (tasks x seeds) are stepped together; each re-planning step makes ONE
`action_fn(obs_batch, task_names) -> (B, K, 4)` call for the still-running episodes, then executes
the first `execute_steps` actions of each chunk. Success = the environment reports success at any step
within the horizon; an episode ends at its first success or at the horizon.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from capvector.core.evaluation.fields import EVAL_FIELDS
from capvector.core.evaluation.video import VIDEO_SUFFIX, Mp4Writer
from capvector.core.simulation.demos import (
    EVAL_SEED_BASE,
    TRAIN_SEED_BASE,
    TRAIN_SEED_SPAN,
    library_versions,
)
from capvector.core.simulation.envs import (
    ACTION_DIM,
    GOAL_SAMPLING,
    MAX_HORIZON,
    EnvConfig,
    MetaWorldEnv,
    ObsMode,
    SharedModel,
    batch_observations,
    expert_policy,
)
from capvector.core.simulation.metaworld_tasks import validate_task_names
from capvector.core.training.execution import ExecutionOnly

ActionFn = Callable[[dict[str, np.ndarray], list[str]], np.ndarray]
Progress = Callable[[int, int], None]
BENCHMARK = "metaworld-v3"


def _field(name: str, **constraints: Any) -> Any:
    """A field whose default and description are `EVAL_FIELDS`' (also `capvector evaluate`'s options)."""
    spec = EVAL_FIELDS[name]
    return Field(spec.default, description=spec.help, **constraints)


class EvalConfig(BaseModel):
    """The evaluation protocol (everything but `batch_size`, `record_video` and `video_size` enters the
    fingerprint: videos are rendered apart from what the policy sees)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    tasks: list[str] = Field(description="Meta-World task names")
    episodes_per_task: int = _field("episodes_per_task", ge=1)
    seed_base: int = Field(EVAL_SEED_BASE, ge=0, description="first goal's env seed (test goals by default)")
    horizon: int = _field("horizon", ge=1, le=MAX_HORIZON)
    obs_mode: ObsMode = _field("obs_mode")
    camera: str = _field("camera")
    image_size: int = _field("image_size", ge=16, le=256)
    execute_steps: int = _field("execute_steps", ge=1)
    # memory: one MjData per env, one model per task
    batch_size: Annotated[int, ExecutionOnly("records equal a one-env-at-a-time loop's")] = _field(
        "batch_size", ge=1
    )
    record_video: int = _field("record_video", ge=0)
    video_size: int = _field("video_size", ge=64, le=1024, multiple_of=16)

    @field_validator("tasks")
    @classmethod
    def _known_tasks(cls, tasks: list[str]) -> list[str]:
        return validate_task_names(tasks)

    @model_validator(mode="after")
    def _disjoint_from_training(self) -> EvalConfig:
        first, last = self.seed_base, self.seed_base + self.episodes_per_task
        if first < TRAIN_SEED_BASE + TRAIN_SEED_SPAN and last > TRAIN_SEED_BASE:
            raise ValueError(
                f"evaluation seeds [{first}, {last}) overlap the demonstration seeds "
                f"[{TRAIN_SEED_BASE}, {TRAIN_SEED_BASE + TRAIN_SEED_SPAN}); use seed_base >= "
                f"{TRAIN_SEED_BASE + TRAIN_SEED_SPAN} "
                "(validation and test bases are in capvector.core.simulation.demos)"
            )
        self.env_config(self.tasks[0])  # validates the camera name
        return self

    @property
    def seeds(self) -> list[int]:
        return [self.seed_base + i for i in range(self.episodes_per_task)]

    def env_config(self, task: str) -> EnvConfig:
        return EnvConfig(
            task=task,
            obs_mode=self.obs_mode,
            camera=self.camera,
            image_size=self.image_size,
            horizon=self.horizon,
        )


class EpisodeRecord(BaseModel):
    task: str
    seed: int
    success: bool
    steps: int  # steps taken: the first success step, or the horizon
    episode_return: float


class EvalResult(BaseModel):
    config: EvalConfig
    fingerprint: str
    protocol: dict
    versions: dict[str, str]
    episodes: list[EpisodeRecord]
    success_rates: dict[str, float]
    mean_success: float
    env_steps: int
    policy_calls: int
    wall_time_s: float
    videos: dict[str, str] = {}  # "<task> seed <goal seed>" -> path of that episode's mp4

    def to_json(self) -> str:
        return self.model_dump_json(indent=1)

    @classmethod
    def from_json(cls, text: str) -> EvalResult:
        return cls.model_validate_json(text)


def protocol_dict(config: EvalConfig) -> dict:
    """The readable protocol: what must match for two scores to be comparable."""
    pixels = config.obs_mode == "pixels"
    return {
        "benchmark": BENCHMARK,
        "metaworld": library_versions()["metaworld"],
        "goal_sampling": GOAL_SAMPLING,
        "tasks": list(config.tasks),
        "horizon": config.horizon,
        "obs_mode": config.obs_mode,
        "camera": config.camera if pixels else None,
        "image_size": config.image_size if pixels else None,
        "episodes_per_task": config.episodes_per_task,
        "seeds": config.seeds,
        "execute_steps": config.execute_steps,
        "success": "info['success'] at any step within the horizon",
    }


def protocol_fingerprint(config: EvalConfig) -> str:
    """sha256 of the canonical JSON of `protocol_dict(config)`."""
    canonical = json.dumps(protocol_dict(config), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()


def expert_action_fn(obs: dict[str, np.ndarray], task_names: list[str]) -> np.ndarray:
    """Meta-World's scripted experts behind the policy interface: chunks of one action, (B, 1, 4),
    clipped to the action box as `envs.expert_action` clips them (one clip for the whole batch)."""
    states = obs["state"]
    raw = [expert_policy(task).get_action(state) for task, state in zip(task_names, states, strict=True)]
    return np.clip(np.array(raw), -1.0, 1.0).astype(np.float32)[:, None, :]


class _EnvPool:
    """Environments reused across batches, built on one `SharedModel` per task: building one env costs
    as much as ~200 simulation steps, and copying a model for each parallel episode even more."""

    def __init__(self, config: EvalConfig):
        self._config = config
        self._shares: dict[str, SharedModel] = {}
        self._free: dict[str, list[MetaWorldEnv]] = {}
        self._all: list[MetaWorldEnv] = []

    def take(self, task: str) -> MetaWorldEnv:
        free = self._free.setdefault(task, [])
        if free:
            return free.pop()
        if task not in self._shares:
            self._shares[task] = SharedModel(self._config.env_config(task))
        env = self._shares[task].new_env()
        self._all.append(env)
        return env

    def give_back(self, envs: list[MetaWorldEnv]) -> None:
        for env in envs:
            self._free[env.task].append(env)

    def close(self) -> None:
        for env in self._all:
            env.close()
        for share in self._shares.values():
            share.close()


def _checked_actions(actions: object, batch: int, execute_steps: int) -> np.ndarray:
    """Fail with the expected shape instead of a broadcasting error deep in the simulator."""
    array = np.asarray(actions, dtype=np.float32)
    if array.ndim != 3 or array.shape[0] != batch or array.shape[2] != ACTION_DIM:
        raise ValueError(
            f"action_fn must return an array of shape (B={batch}, K, {ACTION_DIM}); got shape {array.shape}"
        )
    if array.shape[1] < execute_steps:
        raise ValueError(
            f"action_fn returned chunks of K={array.shape[1]} actions but execute_steps={execute_steps}"
        )
    if not np.all(np.isfinite(array)):
        raise ValueError("action_fn returned NaN or infinite actions")
    return array


class _Rollout:
    """One batch of episodes stepped in lockstep, with per-episode bookkeeping.

    Observations are taken only after the last step of each chunk, while that env holds the shared
    model; images are rendered when the policy is called, and video frames (`video_size`, a renderer
    of their own) every step of the recorded episodes only, each streamed into its episode's mp4."""

    def __init__(
        self,
        envs: list[MetaWorldEnv],
        seeds: list[int],
        horizon: int,
        on_done: Callable[[], None],
        videos: dict[int, Mp4Writer],
        video_size: int,
    ):
        self.envs, self.seeds, self.horizon, self.on_done = envs, seeds, horizon, on_done
        self.videos, self.video_size = videos, video_size  # episode -> its video's writer
        self.tasks = [env.task for env in envs]
        self.pixels = envs[0].config.obs_mode == "pixels"
        self.states = []
        self.privileged = []
        for env, seed in zip(envs, seeds, strict=True):
            self.states.append(env.reset_state(seed))
            self.privileged.append(env.privileged())
        self.returns = [0.0] * len(envs)
        self.success = [False] * len(envs)
        for i, writer in videos.items():
            writer.append(envs[i].render(video_size))
        self.policy_calls = 0

    def _observations(self, rows: list[int]) -> dict[str, np.ndarray]:
        obs = batch_observations([self.states[i] for i in rows], [self.privileged[i] for i in rows])
        if self.pixels:
            obs["image"] = np.stack([self.envs[i].render() for i in rows])
        return obs

    def run(self, action_fn: ActionFn, execute_steps: int) -> None:
        rows = list(range(len(self.envs)))
        while rows:
            chunk = action_fn(self._observations(rows), [self.tasks[i] for i in rows])
            self.policy_calls += 1
            chunk = _checked_actions(chunk, len(rows), execute_steps)
            live = list(enumerate(rows))  # (row of the chunk, episode)
            for k in range(execute_steps):
                last = k == execute_steps - 1
                live = [(row, i) for row, i in live if self._step(i, chunk[row, k], last)]
            rows = [i for _, i in live]

    def _step(self, i: int, action: np.ndarray, observe: bool) -> bool:
        """Step episode `i`; False once it has ended (success or horizon)."""
        env = self.envs[i]
        self.states[i], reward, success, _ = env.step_state(action)
        self.returns[i] += reward
        if i in self.videos:
            self.videos[i].append(env.render(self.video_size))
        if success or env.steps >= self.horizon:
            self.success[i] = success
            self.on_done()
            return False
        if observe:
            self.privileged[i] = env.privileged()
        return True

    def records(self) -> list[EpisodeRecord]:
        return [
            EpisodeRecord(task=env.task, seed=seed, success=ok, steps=env.steps, episode_return=ret)
            for env, seed, ok, ret in zip(self.envs, self.seeds, self.success, self.returns, strict=True)
        ]


def evaluate(
    action_fn: ActionFn,
    config: EvalConfig,
    progress: Progress | None = None,
    video_dir: str | Path | None = None,
) -> EvalResult:
    """Roll out `action_fn` on every task x seed of `config`; videos need `video_dir`."""
    if config.record_video and video_dir is None:
        raise ValueError("record_video needs a video_dir to write the videos into")
    episodes = [(task, seed) for task in config.tasks for seed in config.seeds]
    records: list[EpisodeRecord] = []
    videos: dict[str, str] = {}
    counters = {"done": 0, "policy_calls": 0}

    def on_done() -> None:
        counters["done"] += 1
        if progress is not None:
            progress(counters["done"], len(episodes))

    start = time.perf_counter()
    pool = _EnvPool(config)
    try:
        for first in range(0, len(episodes), config.batch_size):
            batch = episodes[first : first + config.batch_size]
            envs = [pool.take(task) for task, _ in batch]
            writers = _video_writers(batch, config, video_dir)
            try:
                rollout = _Rollout(
                    envs, [seed for _, seed in batch], config.horizon, on_done, writers, config.video_size
                )
                rollout.run(action_fn, config.execute_steps)
            finally:
                written = _close_videos(batch, writers)  # also after an error: no ffmpeg left running
            pool.give_back(envs)
            records.extend(rollout.records())
            counters["policy_calls"] += rollout.policy_calls
            videos.update(written)
    finally:
        pool.close()
    return _result(config, records, videos, counters["policy_calls"], time.perf_counter() - start)


def _video_writers(
    batch: list[tuple[str, int]], config: EvalConfig, video_dir: str | Path | None
) -> dict[int, Mp4Writer]:
    """Episode (row of the batch) -> the writer of its mp4 in `video_dir`, for the recorded episodes:
    the first `record_video` seeds of each task."""
    recorded = [i for i, (_, seed) in enumerate(batch) if seed < config.seed_base + config.record_video]
    if not recorded or video_dir is None:
        return {}
    folder = Path(video_dir)
    folder.mkdir(parents=True, exist_ok=True)
    return {i: Mp4Writer(folder / f"{batch[i][0]}-seed{batch[i][1]}{VIDEO_SUFFIX}") for i in recorded}


def _close_videos(batch: list[tuple[str, int]], writers: dict[int, Mp4Writer]) -> dict[str, str]:
    """End the batch's videos; `EvalResult.videos`' entries ("<task> seed <goal seed>" -> path)."""
    return {
        f"{batch[i][0]} seed {batch[i][1]}": str(writer.close())
        for i, writer in writers.items()
        if writer.frames
    }


def _result(
    config: EvalConfig, records: list[EpisodeRecord], videos: dict[str, str], policy_calls: int, wall: float
) -> EvalResult:
    rates = {task: float(np.mean([r.success for r in records if r.task == task])) for task in config.tasks}
    return EvalResult(
        config=config,
        fingerprint=protocol_fingerprint(config),
        protocol=protocol_dict(config),
        versions=library_versions(),
        episodes=records,
        success_rates=rates,
        mean_success=float(np.mean(list(rates.values()))),
        env_steps=sum(r.steps for r in records),
        policy_calls=policy_calls,
        wall_time_s=wall,
        videos=videos,
    )
