"""Meta-World task tables, seeded goal variations, observation contract, upright rendering, envs on
a shared model."""

import numpy as np
import pytest
from pydantic import ValidationError

from capvector.core.simulation.demos import EVAL_SEED_BASE, TRAIN_SEED_BASE
from capvector.core.simulation.envs import (
    EPISODE_MODEL_FIELDS,
    EnvConfig,
    MetaWorldEnv,
    SharedModel,
    _compiled_model,
    expert_action,
)
from capvector.core.simulation.metaworld_tasks import (
    DIFFICULTY_GROUPS,
    INSTRUCTIONS,
    TASK_NAMES,
    check_against_metaworld,
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


def test_the_task_tables_match_metaworlds_registry_and_a_drift_fails_loudly(monkeypatch):
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    assert set(TASK_NAMES) == set(ALL_V3_ENVIRONMENTS)
    check_against_metaworld.cache_clear()
    monkeypatch.setitem(ALL_V3_ENVIRONMENTS, "new-task-v3", object)  # a metaworld upgrade adds a task
    with pytest.raises(RuntimeError, match="new-task-v3"):
        check_against_metaworld()
    check_against_metaworld.cache_clear()


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


def _round_robin(envs: list[MetaWorldEnv], seeds: list[int], steps: int) -> list[list[tuple]]:
    """Expert rollouts stepped in turn; per env, per step: (state, privileged, goal, reward, success)."""
    trace = [[(obs["state"], obs["privileged"], env.goal, 0.0, False)] for env, obs in _resets(envs, seeds)]
    for _ in range(steps):
        for env, history in zip(envs, trace, strict=True):
            obs, reward, success, _ = env.step(expert_action(env.task, history[-1][0]))
            history.append((obs["state"], obs["privileged"], env.goal, reward, success))
    return trace


def _resets(envs, seeds):
    return [(env, env.reset(seed)) for env, seed in zip(envs, seeds, strict=True)]


@pytest.mark.parametrize("task", ["drawer-open-v3", "pick-place-v3"])
def test_envs_on_a_shared_model_compute_what_envs_with_their_own_model_do(task):
    """These tasks move bodies and sites in the model at reset; stepped in turn, each shared env must
    still see its own (a wrong swap changes their trajectories)."""
    seeds = [EVAL_SEED_BASE + i for i in range(3)]
    own = [MetaWorldEnv(EnvConfig(task=task)) for _ in seeds]
    expected = [_round_robin([env], [seed], 30)[0] for env, seed in zip(own, seeds, strict=True)]
    share = SharedModel(EnvConfig(task=task))
    envs = [share.new_env(), share.new_env()]
    envs[0].reset(seeds[0])
    envs.append(share.new_env())  # built while another env holds episode values in the model
    assert len({id(env.env.model) for env in envs}) == 1
    shared = _round_robin(envs, seeds, 30)
    for got, want in zip(shared, expected, strict=True):
        for got_step, want_step in zip(got, want, strict=True):
            for a, b in zip(got_step, want_step, strict=True):
                np.testing.assert_array_equal(a, b)
    for env in own + envs:
        env.close()
    share.close()


def test_bvh_viewer_flag_is_off_and_changes_no_trajectory():
    """Envs skip MuJoCo's per-step clearing of the viewer's BVH flags: same physics as with it on."""
    with (
        MetaWorldEnv(EnvConfig(task="pick-place-v3")) as off,
        MetaWorldEnv(EnvConfig(task="pick-place-v3")) as on,
    ):
        assert off.env.model.vis.global_.bvactive == 0
        on.env.model.vis.global_.bvactive = 1
        traces = [_round_robin([env], [EVAL_SEED_BASE], 60)[0] for env in (off, on)]
        assert on.env.data.bvh_active.any() and not off.env.data.bvh_active.any()
    for got_step, want_step in zip(*traces, strict=True):
        for a, b in zip(got_step, want_step, strict=True):
            np.testing.assert_array_equal(a, b)


def test_shared_model_renders_each_env_own_scene():
    config = EnvConfig(task="drawer-close-v3", obs_mode="pixels", image_size=32)
    share = SharedModel(config)
    shared = [share.new_env(), share.new_env()]
    own = [MetaWorldEnv(config), MetaWorldEnv(config)]
    images = []
    for envs in (shared, own):
        first = [env.reset(seed)["image"] for env, seed in zip(envs, [1, 2], strict=True)]
        envs[1].step(np.array([0.0, 0.0, 1.0, 0.0]))
        images.append((first, envs[0].render(), envs[1].render()))  # env 0 renders while env 1 held the model
    (first, zero, one), (own_first, own_zero, own_one) = images
    np.testing.assert_array_equal(zero, own_zero)
    np.testing.assert_array_equal(one, own_one)
    assert all(np.array_equal(a, b) for a, b in zip(first, own_first, strict=True))
    assert not np.array_equal(own_first[0], own_first[1])  # two goal variations look different
    for env in shared + own:
        env.close()
    share.close()


def _model_arrays(model) -> dict[str, np.ndarray]:
    names = [name for name in dir(model) if not name.startswith("_")]
    return {
        name: getattr(model, name).copy() for name in names if isinstance(getattr(model, name), np.ndarray)
    }


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return np.array_equal(a, b, equal_nan=a.dtype.kind == "f")  # some compiled arrays hold NaN


def test_meta_world_writes_only_the_episode_fields_into_its_model():
    """`SharedModel` swaps only EPISODE_MODEL_FIELDS between envs: on every task, construction,
    resets and steps must leave the rest of the model as compiled."""
    for task in TASK_NAMES:
        with MetaWorldEnv(EnvConfig(task=task)) as env:
            for seed in (EVAL_SEED_BASE, EVAL_SEED_BASE + 1):
                obs = env.reset(seed)
                for _ in range(5):
                    obs, *_ = env.step(expert_action(task, obs["state"]))
            compiled = _model_arrays(_compiled_model(env.env.fullpath))
            now = _model_arrays(env.env.model)
        changed = {name for name in compiled if not _same(compiled[name], now[name])}
        assert changed <= set(EPISODE_MODEL_FIELDS), (task, changed - set(EPISODE_MODEL_FIELDS))
