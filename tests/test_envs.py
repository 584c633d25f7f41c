"""Meta-World task tables, seeded goal variations, observation contract, upright rendering."""

import numpy as np
import pytest
from pydantic import ValidationError

from capvector_core.demos import EVAL_SEED_BASE, TRAIN_SEED_BASE
from capvector_core.envs import EnvConfig, MetaWorldEnv, expert_action
from capvector_core.metaworld_tasks import (
    DIFFICULTY_GROUPS,
    INSTRUCTIONS,
    TASK_NAMES,
    difficulty,
    validate_task_names,
)


def test_fifty_tasks_each_with_instruction_and_one_group():
    assert len(TASK_NAMES) == 50 and all(name.endswith("-v3") for name in TASK_NAMES)
    assert set(INSTRUCTIONS) == set(TASK_NAMES)
    assert sorted(t for group in DIFFICULTY_GROUPS.values() for t in group) == sorted(TASK_NAMES)
    sizes = {k: len(v) for k, v in DIFFICULTY_GROUPS.items()}
    assert sizes == {"easy": 28, "medium": 11, "hard": 6, "very_hard": 5}
    assert difficulty("pick-place-v3") == "hard"


def test_unknown_task_names_are_named_with_suggestions():
    with pytest.raises(ValueError, match=r"'pick-place-v2' \(did you mean pick-place-v3") as err:
        validate_task_names(["reach-v3", "pick-place-v2", "nonsense"])
    assert "'nonsense'" in str(err.value)
    with pytest.raises(ValidationError, match="unknown Meta-World v3 task"):
        EnvConfig(task="reach")


@pytest.mark.parametrize(
    "bad", [{"image_size": 8}, {"image_size": 512}, {"horizon": 501}, {"camera": "nope"}, {"obs_mode": "rgb"}]
)
def test_impossible_env_configs_are_rejected(bad):
    with pytest.raises(ValidationError):
        EnvConfig(task="reach-v3", **bad)


@pytest.fixture(scope="module")
def state_env():
    with MetaWorldEnv(EnvConfig(task="pick-place-v3", horizon=100)) as env:
        yield env


def test_goal_variation_is_a_function_of_the_seed(state_env):
    first = state_env.reset(7)
    goal = state_env.goal
    state_env.step(np.array([1.0, 0.0, 0.0, 0.0]))
    again = state_env.reset(7)
    np.testing.assert_array_equal(first["state"], again["state"])
    np.testing.assert_array_equal(goal, state_env.goal)
    state_env.reset(8)
    assert not np.allclose(goal, state_env.goal)
    # a fresh env gives the same goal for the same seed
    with MetaWorldEnv(EnvConfig(task="pick-place-v3")) as other:
        np.testing.assert_array_equal(other.reset(7)["state"], first["state"])


def test_training_and_evaluation_seeds_give_different_goals(state_env):
    def goals(base):
        out = []
        for i in range(10):
            state_env.reset(base + i)
            out.append(np.concatenate([state_env.goal, state_env.privileged()[:3]]))
        return np.array(out)

    train, evaluation = goals(TRAIN_SEED_BASE), goals(EVAL_SEED_BASE)
    distances = np.linalg.norm(train[:, None] - evaluation[None], axis=-1)
    assert distances.min() > 1e-4
    assert len(np.unique(train.round(6), axis=0)) == 10


def test_state_observation_contract(state_env):
    obs = state_env.reset(3)
    assert set(obs) == {"state", "proprio", "privileged"}
    for key, dim in [("state", 39), ("proprio", 4), ("privileged", 9)]:
        assert obs[key].shape == (dim,) and obs[key].dtype == np.float32
    np.testing.assert_allclose(obs["proprio"], obs["state"][:4])
    np.testing.assert_allclose(obs["privileged"][3:6], obs["state"][-3:], atol=1e-6)  # goal
    np.testing.assert_allclose(obs["privileged"][0:3], obs["state"][4:7], atol=1e-5)  # object
    obs, reward, success, info = state_env.step(expert_action("pick-place-v3", obs["state"]))
    assert isinstance(reward, float) and isinstance(success, bool) and "success" in info


def test_bad_actions_and_overlong_episodes_fail_clearly():
    with MetaWorldEnv(EnvConfig(task="reach-v3", horizon=2)) as env:
        env.reset(0)
        with pytest.raises(ValueError, match="4 finite numbers"):
            env.step(np.array([0.0, np.nan, 0.0, 0.0]))
        env.step(np.zeros(4))
        env.step(np.zeros(4))
        with pytest.raises(RuntimeError, match="horizon of 2"):
            env.step(np.zeros(4))


@pytest.fixture(scope="module")
def pixel_env():
    with MetaWorldEnv(EnvConfig(task="reach-v3", obs_mode="pixels", image_size=64)) as env:
        yield env


def test_pixel_observation_contract(pixel_env):
    obs = pixel_env.reset(1)
    assert obs["image"].shape == (64, 64, 3) and obs["image"].dtype == np.uint8
    assert obs["image"].std() > 5  # a scene, not a blank frame
    assert obs["state"].shape == (39,) and obs["privileged"].shape == (9,)


def test_images_are_upright(pixel_env):
    """Lifting the hand must move it up in the image; the raw corner camera image is rotated."""
    pixel_env.reset(2)
    upright = pixel_env.render()
    raw = pixel_env._renderer._renderer.render()  # scene already updated by render()
    np.testing.assert_array_equal(upright, raw[::-1, ::-1])
    # the red arm's pixels move up in the image when the hand goes up in the world
    pixel_env.reset(2)
    low = _arm_mean_row(pixel_env.render())
    for _ in range(25):
        pixel_env.step(np.array([0.0, 0.0, 1.0, 0.0]))
    high = _arm_mean_row(pixel_env.render())
    assert high < low - 1, (low, high)


def _arm_mean_row(image: np.ndarray) -> float:
    """Mean row of the arm's (strongly red) pixels."""
    rgb = image.astype(np.int32)
    red = (rgb[..., 0] > 120) & (rgb[..., 0] > rgb[..., 1] + 60) & (rgb[..., 0] > rgb[..., 2] + 60)
    rows = np.nonzero(red)[0]
    assert rows.size > 20, "the red Sawyer arm should be visible"
    return float(rows.mean())
