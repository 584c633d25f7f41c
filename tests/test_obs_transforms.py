"""The observation transform: seeded and rebuilt identically, part of the policy (not its weights),
declared once in the pipeline config, and refused where it cannot apply."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from capvector.core.policies.base import build_policy, load_policy, save_policy
from capvector.core.simulation.obs_transforms import POSITIONS, ObsTransform, ObsTransformConfig
from capvector.flows.study.config import load_study

POLICY = {"obs_mode": "state", "d_model": 32, "n_layers": 1, "n_heads": 2, "chunk_size": 4}
RANDOM = {"kind": "random_features", "features": 40, "distractors": 10, "seed": 3}


def test_the_map_is_fixed_by_its_seed_and_hides_the_state_behind_sines():
    state = torch.randn(6, 39)
    a = ObsTransform(ObsTransformConfig(**RANDOM), 39)(state)
    b = ObsTransform(ObsTransformConfig(**RANDOM), 39)(state)
    other = ObsTransform(ObsTransformConfig(**{**RANDOM, "seed": 4}), 39)(state)
    assert a.shape == (6, 50) and torch.equal(a, b) and not torch.allclose(a, other)
    assert a.abs().max() <= 1.0  # sines: the positions are not in the input in clear
    moved = state.clone()
    moved[:, POSITIONS["goal"][0]] += 0.05  # the distractors move a lot for a small goal shift
    shift = (ObsTransform(ObsTransformConfig(**RANDOM), 39)(moved) - a)[:, 40:].abs().mean()
    assert shift > 0.3
    hidden = ObsTransformConfig(**{**RANDOM, "aliased": ["goal", "object"], "hide_aliased": True})
    assert hidden.aliased_dims() == [4, 5, 6, 22, 23, 24, 36, 37, 38]
    shown = ObsTransform(hidden, 39)
    features = shown(moved)[:, :40] - shown(state)[:, :40]
    assert features.abs().max() < 1e-6  # a hidden position moves only the distractors
    identity = ObsTransform(ObsTransformConfig(), 39)
    assert identity(state) is state


def test_a_policy_saves_the_transform_in_its_config_not_its_weights(tmp_path):
    plain = build_policy(POLICY, device="cpu")
    mapped = build_policy({**POLICY, "obs_transform": RANDOM}, device="cpu")
    assert mapped.config.n_obs_tokens == 5 and plain.config.n_obs_tokens == 5
    assert not any("transform" in k for k in mapped.state_dict())
    path = save_policy(mapped, tmp_path / "p.safetensors")
    again = load_policy(path, device="cpu")
    assert again.config.obs_transform == mapped.config.obs_transform
    obs = {
        "state": np.random.default_rng(0).normal(size=(2, 39)).astype(np.float32),
        "proprio": np.zeros((2, 4), np.float32),
    }
    mapped.fit_normalizer(
        {"state": torch.randn(50, 39), "proprio": torch.randn(50, 4), "action": torch.randn(50, 4)}
    )
    path = save_policy(mapped, tmp_path / "fitted.safetensors")
    np.testing.assert_array_equal(
        load_policy(path, device="cpu").predict_action_chunk(obs, ["reach-v3"] * 2),
        mapped.predict_action_chunk(obs, ["reach-v3"] * 2),
    )


def test_the_pipeline_declares_it_once_and_refuses_what_cannot_run():
    config = load_study("study-smoke", ["data.obs_transform.kind=random_features"])
    assert config.policy.obs_transform == config.data.obs_transform
    assert config.policy.obs_transform.active
    with pytest.raises(ValueError, match="divisible by tokens"):
        load_study("study-smoke", ["data.obs_transform.kind=random_features", "data.obs_transform.tokens=7"])
    with pytest.raises(ValueError, match="set data.obs_transform only"):
        load_study("study-smoke", ["policy.obs_transform.kind=random_features", "data.obs_transform.seed=5"])
    with pytest.raises(ValueError, match="frequency"):
        load_study("study-smoke", ["data.obs_transform.frequency=nan"])
