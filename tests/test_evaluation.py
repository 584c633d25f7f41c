"""Batched evaluation: expert success, records equal to a one-env-at-a-time loop, protocol
fingerprint, bad policy outputs, videos."""

import imageio.v3 as iio
import numpy as np
import pytest
from pydantic import ValidationError

from capvector.core.evaluation.fields import EVAL_FIELDS
from capvector.core.evaluation.rollouts import (
    EpisodeRecord,
    EvalConfig,
    EvalResult,
    evaluate,
    expert_action_fn,
    protocol_dict,
    protocol_fingerprint,
)
from capvector.core.simulation.demos import EVAL_SEED_BASE, VALIDATION_SEED_BASE
from capvector.core.simulation.envs import MetaWorldEnv

TASKS = ["reach-v3", "drawer-close-v3"]


@pytest.fixture(scope="module")
def expert_result():
    calls = []

    def counting_expert(obs, task_names):
        calls.append(len(task_names))
        assert obs["state"].shape == (len(task_names), 39) and "privileged" in obs
        return expert_action_fn(obs, task_names)

    config = EvalConfig(tasks=TASKS, episodes_per_task=3, horizon=150, batch_size=4)
    return evaluate(counting_expert, config), calls


def test_expert_succeeds_and_records_are_complete(expert_result):
    result, calls = expert_result
    assert result.success_rates == {"reach-v3": 1.0, "drawer-close-v3": 1.0} and result.mean_success == 1.0
    assert [(r.task, r.seed) for r in result.episodes] == [
        (task, EVAL_SEED_BASE + i) for task in TASKS for i in range(3)
    ]
    assert all(r.success and 0 < r.steps < 150 and r.episode_return > 0 for r in result.episodes)
    assert result.env_steps == sum(r.steps for r in result.episodes)
    # batches of at most 4 envs; one policy call per step for the still-running ones
    assert max(calls) == 4 and result.policy_calls == len(calls)
    assert set(result.versions) == {"metaworld", "mujoco", "numpy", "torch"}


def straightforward_records(action_fn, config: EvalConfig) -> list[EpisodeRecord]:
    """The obvious loop: one env of its own per task, one episode at a time, public API only."""
    records = []
    for task in config.tasks:
        with MetaWorldEnv(config.env_config(task)) as env:
            for seed in config.seeds:
                obs, episode_return, success = env.reset(seed), 0.0, False
                while not success and env.steps < config.horizon:
                    chunk = action_fn({key: value[None] for key, value in obs.items()}, [task])
                    for action in chunk[0, : config.execute_steps]:
                        obs, reward, success, _ = env.step(action)
                        episode_return += reward
                        if success or env.steps >= config.horizon:
                            break
                records.append(
                    EpisodeRecord(
                        task=task, seed=seed, success=success, steps=env.steps, episode_return=episode_return
                    )
                )
    return records


def jittered_chunks(obs, task_names):
    """Chunks of 3 expert-based actions that differ within the chunk (per-row, batch-independent)."""
    actions = np.repeat(expert_action_fn(obs, task_names), 3, axis=1)
    actions[:, 1:, :3] *= np.float32(0.9)
    return actions


@pytest.mark.parametrize(
    ("action_fn", "execute_steps", "batch_size"),
    [(expert_action_fn, 1, 5), (jittered_chunks, 3, 4)],
    ids=["expert", "chunks"],
)
def test_batched_evaluation_gives_the_records_of_a_one_env_at_a_time_loop(
    action_fn, execute_steps, batch_size
):
    """Lockstep batches on shared models (drawer and pick-place write episode values into theirs),
    envs reused across batches, observations built only for policy calls: none may change a record."""
    config = EvalConfig(
        tasks=["drawer-open-v3", "pick-place-v3", "reach-v3"],
        episodes_per_task=3,
        horizon=120,
        execute_steps=execute_steps,
        batch_size=batch_size,
    )
    result = evaluate(action_fn, config)
    assert result.episodes == straightforward_records(action_fn, config)
    assert result.env_steps == sum(r.steps for r in result.episodes)


def test_result_json_roundtrip(expert_result):
    result, _ = expert_result
    assert EvalResult.from_json(result.to_json()) == result


def test_fingerprint_tracks_the_protocol_only():
    base = EvalConfig(tasks=TASKS, episodes_per_task=3, horizon=150)
    fingerprint = protocol_fingerprint(base)
    assert len(fingerprint) == 64
    changes = [
        {"horizon": 100},
        {"episodes_per_task": 4},
        {"execute_steps": 2},
        {"obs_mode": "pixels"},
        {"seed_base": VALIDATION_SEED_BASE},
        {"tasks": ["reach-v3"]},
    ]
    for change in changes:
        assert protocol_fingerprint(base.model_copy(update=change)) != fingerprint, change
    not_protocol = base.model_copy(update={"batch_size": 7, "record_video": True, "video_size": 512})
    assert protocol_fingerprint(not_protocol) == fingerprint
    pixels = base.model_copy(update={"obs_mode": "pixels"})
    assert protocol_fingerprint(pixels.model_copy(update={"image_size": 96})) != protocol_fingerprint(pixels)
    readable = protocol_dict(base)
    assert readable["benchmark"] == "metaworld-v3"
    assert readable["seeds"] == [EVAL_SEED_BASE + i for i in range(3)]


def test_action_chunks_are_executed_as_configured():
    calls = []

    def chunked_expert(obs, task_names):
        calls.append(1)
        return np.repeat(expert_action_fn(obs, task_names), 4, axis=1)  # (B, 4, 4): repeat the action

    config = EvalConfig(tasks=["reach-v3"], episodes_per_task=2, horizon=60, execute_steps=4)
    result = evaluate(chunked_expert, config)
    assert len(calls) == result.policy_calls == -(-max(r.steps for r in result.episodes) // 4)


@pytest.mark.parametrize(
    ("output", "message"),
    [
        (lambda b: np.zeros((b, 4)), r"shape \(B=2, K, 4\); got shape \(2, 4\)"),
        (lambda b: np.zeros((b, 1, 3)), r"got shape \(2, 1, 3\)"),
        (lambda b: np.zeros((b + 1, 1, 4)), r"got shape \(3, 1, 4\)"),
        (lambda b: np.full((b, 1, 4), np.nan), "NaN or infinite"),
        (lambda b: np.zeros((b, 1, 4)), "K=1 actions but execute_steps=2"),
    ],
)
def test_wrong_policy_outputs_fail_clearly(output, message):
    execute = 2 if "execute_steps" in message else 1
    config = EvalConfig(tasks=["reach-v3"], episodes_per_task=2, horizon=10, execute_steps=execute)
    with pytest.raises(ValueError, match=message):
        evaluate(lambda obs, names: output(len(names)), config)


def test_evaluation_seeds_may_not_overlap_demo_seeds():
    with pytest.raises(ValidationError, match="overlap the demonstration seeds"):
        EvalConfig(tasks=["reach-v3"], seed_base=0)


@pytest.mark.parametrize(
    ("obs_mode", "video_size"), [("pixels", None), ("state", 224)], ids=["pixels-default-size", "state-224"]
)
def test_recorded_episode_is_an_mp4_and_changes_nothing(tmp_path, obs_mode, video_size):
    """A real episode of each task's first seed as an H.264 mp4 at the video size (one frame at reset,
    one per step), while the policy sees its own 32 px images and every record equals a run without."""
    protocol = {"tasks": ["reach-v3"], "episodes_per_task": 2, "horizon": 12, "obs_mode": obs_mode}
    protocol |= {"image_size": 32} | ({"video_size": video_size} if video_size else {})
    config = EvalConfig(**protocol, record_video=1)
    side = video_size or EVAL_FIELDS["video_size"].default
    assert side >= 224

    def run(config, **kw):
        seen = []

        def expert_checking_images(obs, task_names):
            seen.append(obs["image"].copy() if obs_mode == "pixels" else obs["state"].copy())
            return expert_action_fn(obs, task_names)

        return evaluate(expert_checking_images, config, **kw), seen

    result, seen = run(config, video_dir=tmp_path)
    plain, plain_seen = run(config.model_copy(update={"record_video": 0}))
    assert result.episodes == plain.episodes and result.success_rates == plain.success_rates
    assert all(np.array_equal(a, b) for a, b in zip(seen, plain_seen, strict=True))
    if obs_mode == "pixels":
        assert seen[0].shape == (2, 32, 32, 3)
    assert plain.videos == {} and list(result.videos) == [f"reach-v3 seed {EVAL_SEED_BASE}"]
    path = tmp_path / f"reach-v3-seed{EVAL_SEED_BASE}.mp4"
    assert result.videos[f"reach-v3 seed {EVAL_SEED_BASE}"] == str(path)
    frames = iio.imread(path, plugin="FFMPEG", index=None)
    assert frames.shape == (result.episodes[0].steps + 1, side, side, 3)
    assert frames.mean() > 20  # a scene, not a black frame
    assert iio.immeta(path, plugin="FFMPEG")["codec"] == "h264"
    with pytest.raises(ValueError, match="needs a video_dir"):
        evaluate(expert_action_fn, config)


def test_video_size_must_suit_the_encoder():
    with pytest.raises(ValidationError, match="video_size"):
        EvalConfig(tasks=["reach-v3"], video_size=250)
