"""Auxiliary objectives: registry, finite losses, grads only where expected, heads kept out of the policy."""

import pytest
import torch

from capvector.core.policies.base import build_policy
from capvector.core.policies.tokenizer import encode_batch
from capvector.core.training.aux_objectives import (
    build_objective,
    get_objective,
    known_objectives,
    register_objective,
)

TINY = dict(d_model=32, n_layers=4, n_heads=4, chunk_size=3, vocab_size=64, max_instruction_tokens=6)


def features(**config):
    return build_policy({**TINY, **config}, "cpu").feature_specs()


def batch(config, b=6):
    return {
        "actions": torch.randn(b, config.chunk_size, 4),
        "tokens": encode_batch(["push the puck"] * b, config.vocab_size, config.max_instruction_tokens),
        "state": torch.randn(b, 39),
        "proprio": torch.randn(b, 4),
        "image": torch.randint(0, 256, (b, config.image_size, config.image_size, 3), dtype=torch.uint8),
        "privileged": torch.randn(b, 9),
        "privileged_future": torch.randn(b, 9),
    }


def test_registry():
    assert {"spatial", "dynamics"} <= set(known_objectives())
    with pytest.raises(
        ValueError, match=r"unknown auxiliary objective 'nope'; known: \[.*'dynamics'.*'spatial'"
    ):
        get_objective("nope")
    with pytest.raises(ValueError, match="already registered"):
        register_objective("spatial")(get_objective("spatial"))
    with pytest.raises(ValueError, match="n_layers=4"):
        build_objective("spatial", features(), {"layer": 7})
    with pytest.raises(ValueError, match="extra"):
        build_objective("dynamics", features(), {"horizn": 3})


@pytest.mark.parametrize("policy_type", ["l1_chunk", "flow"])
@pytest.mark.parametrize(
    "mode,name,params",
    [
        ("state", "spatial", {"pooling": "token"}),
        ("state", "spatial", {"pooling": "mean", "layer": 1}),
        ("pixels", "spatial", {}),
        ("state", "dynamics", {"horizon": 2}),
    ],
)
def test_loss_finite_grads_where_expected_and_heads_separate(policy_type, mode, name, params):
    policy = build_policy(
        {"type": policy_type, "obs_mode": mode, "image_size": 16, "stem_channels": [8, 8], **TINY}, "cpu"
    )
    config = policy.config
    keys_before = set(policy.state_dict())
    objective = build_objective(name, policy.feature_specs(), params)
    b = batch(config)
    objective.fit({"privileged": torch.randn(50, 9) * 3 + 1})
    loss = objective(policy.compute_loss(b, objective.feature_names).features, b)
    assert loss.ndim == 0 and torch.isfinite(loss)
    loss.backward()
    assert set(policy.state_dict()) == keys_before  # heads are not policy weights
    assert all(p.grad is not None for p in objective.head.parameters())
    assert not any(p.requires_grad for p in objective.buffers())
    grads = {k: p.grad for k, p in policy.named_parameters()}
    # never reaches the action head; spatial at layer L leaves later layers untouched
    assert grads["action_head.proj.weight"] is None
    if name == "spatial":
        layer = objective.layer
        assert grads[f"backbone.layers.{layer}.mlp.fc2.weight"] is not None
        if layer + 1 < config.n_layers:
            assert grads[f"backbone.layers.{layer + 1}.attn.q_proj.weight"] is None
        obs = "vision.stem.0.weight" if mode == "pixels" else "state.proj.obj1.weight"
        assert grads[obs].abs().sum() > 0
    if name == "dynamics":
        assert objective.horizon == 2 and objective.required_fields() == ["privileged"]


def test_spatial_required_fields_and_default_layer():
    assert build_objective("spatial", features()).required_fields() == ["privileged"]
    spatial = build_objective("spatial", features(obs_mode="pixels", image_size=16, stem_channels=[8, 8]))
    assert spatial.required_fields() == ["privileged"]  # the image is the policy's own requirement
    assert spatial.token_pos.shape[0] == 16  # one position per vision token of the 4x4 grid
    assert spatial.layer == 2  # 3/4 depth of 4 layers (SF: an intermediate, fairly deep layer)


def test_objective_refuses_a_policy_without_its_feature():
    with pytest.raises(ValueError, match=r"needs policy feature\(s\) \['obs_tokens'\]"):
        build_objective("spatial", {"tokens": features()["tokens"]})


def test_spatial_target_is_fixed():
    a, b = build_objective("spatial", features()), build_objective("spatial", features())
    x = torch.randn(4, 9)
    assert torch.equal(a.target(x), b.target(x))
    assert not any("fourier" in n for n, _ in a.named_parameters())


@pytest.mark.parametrize("name", ["spatial", "dynamics"])
def test_heads_built_with_a_seed_leave_the_global_rng_alone(name):
    """With a seed (the trainer passes the run's), an objective's heads come from a generator of their
    own: the same heads for the same seed, and torch's global RNG draws next what it would have."""
    specs = features()
    torch.manual_seed(11)
    expected = torch.rand(3)
    torch.manual_seed(11)
    a = build_objective(name, specs, seed=4)
    assert torch.equal(torch.rand(3), expected)
    b, c = build_objective(name, specs, seed=4), build_objective(name, specs, seed=5)
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert not all(torch.equal(sa[k], sc[k]) for k in sa)
    torch.manual_seed(4)  # the seed's stream, as before: the heads the trainer built from it then
    d = build_objective(name, specs)
    assert all(torch.equal(v, d.state_dict()[k]) for k, v in sa.items())
