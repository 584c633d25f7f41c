"""Policies: the interface on both built-in types, stable names, exact save/load, dispatch, errors."""

import json

import numpy as np
import pytest
import torch
from pydantic import ValidationError

from capvector.core.policies import FlowConfig, FlowPolicy, L1ChunkConfig, L1ChunkPolicy, tokenizer
from capvector.core.policies.base import (
    CONFIG_METADATA_KEY,
    build_policy,
    load_policy,
    load_policy_weights,
    parse_policy_config,
    policy_types,
    read_metadata,
    save_policy,
    save_tensors_atomic,
)

TINY = dict(d_model=32, n_layers=2, n_heads=4, chunk_size=3, vocab_size=64, max_instruction_tokens=6)
TYPES = ["l1_chunk", "flow"]


def batch(config, b: int = 5) -> dict:
    return {
        "tokens": tokenizer.encode_batch(
            ["open the door"] * b, config.vocab_size, config.max_instruction_tokens
        ),
        "state": torch.randn(b, 39),
        "proprio": torch.randn(b, 4),
        "image": torch.randint(0, 256, (b, config.image_size, config.image_size, 3), dtype=torch.uint8),
        "actions": torch.rand(b, config.chunk_size, 4) * 2 - 1,
    }


def fitted(policy):
    policy.normalizer.set_stats(
        {k: (torch.randn(d), torch.rand(d) + 0.5) for k, d in [("state", 39), ("proprio", 4), ("action", 4)]}
    )
    return policy


@pytest.mark.parametrize("policy_type", TYPES)
@pytest.mark.parametrize("mode,n_obs", [("state", 5), ("pixels", 4)])
def test_loss_and_features(policy_type, mode, n_obs):
    config = {"type": policy_type, "obs_mode": mode, "image_size": 32, "stem_channels": [8, 8, 8, 8], **TINY}
    policy = build_policy(config, "cpu")
    out = policy.compute_loss(batch(policy.config), ["obs_tokens", "tokens"])
    assert out.loss.ndim == 0 and torch.isfinite(out.loss) and set(out.terms) == {"action"}
    specs = policy.feature_specs()
    assert specs["obs_tokens"].n_tokens == n_obs
    assert [f.shape for f in out.features["obs_tokens"]] == [(5, n_obs, 32)] * 2
    assert out.features["tokens"][0].shape == (5, specs["tokens"].n_tokens, 32)
    out.loss.backward()
    assert policy.action_head.proj.weight.grad is not None
    with pytest.raises(ValueError, match="no feature"):
        policy.compute_loss(batch(policy.config), ["depth"])


def test_parameter_names_are_stable():
    keys = set(L1ChunkPolicy(L1ChunkConfig(**TINY)).state_dict())
    shared = [
        "language.embed.weight",
        "state.proj.hand.weight",
        "state.proj.goal.bias",
        "proprio.proj.weight",
        "embeddings.position",
        "embeddings.token_type.weight",
        "backbone.layers.0.attn.q_proj.weight",
        "backbone.layers.1.attn.o_proj.bias",
        "backbone.layers.0.mlp.fc1.weight",
        "backbone.layers.0.norm1.weight",
        "backbone.norm.weight",
        "action_head.proj.weight",
        "normalizer.action_std",
        "normalizer.fitted",
    ]
    for key in [*shared, "embeddings.action_queries"]:
        assert key in keys, key
    flow = set(FlowPolicy(FlowConfig(**TINY)).state_dict())
    for key in [
        *shared,
        "action_expert.action_in.weight",
        "action_expert.time_mlp_in.weight",
        "action_expert.position",
        "action_expert.layers.1.attn.k_proj.weight",
        "action_expert.layers.0.mlp.fc2.bias",
        "action_expert.norm.weight",
    ]:
        assert key in flow, key
    assert "embeddings.action_queries" not in flow
    pixels = set(L1ChunkPolicy(L1ChunkConfig(obs_mode="pixels", image_size=32, **TINY)).state_dict())
    assert {"vision.stem.0.weight", "vision.proj.weight"} <= pixels
    assert not any(k.startswith("state.") for k in pixels)


@pytest.mark.parametrize("policy_type", TYPES)
def test_save_load_roundtrip_is_exact_and_dispatches_on_type(tmp_path, policy_type):
    model = fitted(build_policy({"type": policy_type, "obs_mode": "pixels", "image_size": 32, **TINY}, "cpu"))
    path = save_policy(model, tmp_path / "p.safetensors", metadata={"note": "hi"})
    meta = read_metadata(path)
    assert meta["note"] == "hi" and json.loads(meta[CONFIG_METADATA_KEY])["type"] == policy_type
    loaded = load_policy(path, device="cpu")
    assert type(loaded) is type(model) and loaded.config == model.config
    for k, v in model.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k]), k
    obs = {"image": batch(model.config)["image"].numpy(), "proprio": np.zeros((5, 4), np.float32)}
    tasks = ["reach-v3"] * 5
    assert np.array_equal(model.predict_action_chunk(obs, tasks), loaded.predict_action_chunk(obs, tasks))


def test_a_file_from_before_policy_types_loads_as_l1_chunk(tmp_path):
    model = L1ChunkPolicy(L1ChunkConfig(**TINY))
    old_config = model.config.model_dump(mode="json", exclude={"type"})
    tensors = {k: v.contiguous() for k, v in model.state_dict().items()}
    save_tensors_atomic(tensors, tmp_path / "old.safetensors", {CONFIG_METADATA_KEY: json.dumps(old_config)})
    assert isinstance(load_policy(tmp_path / "old.safetensors", "cpu"), L1ChunkPolicy)


def test_unknown_type_names_the_known_ones():
    assert {"l1_chunk", "flow"} <= set(policy_types())
    with pytest.raises(ValueError, match=r"unknown policy type 'pi0'; known: \[.*'flow'.*'l1_chunk'"):
        parse_policy_config({"type": "pi0"})
    with pytest.raises(ValidationError, match="integration_steps"):
        parse_policy_config({"type": "l1_chunk", "integration_steps": 4})  # a flow-only field


def test_config_mismatch_names_keys_and_shapes(tmp_path):
    path = save_policy(L1ChunkPolicy(L1ChunkConfig(**TINY)), tmp_path / "p.safetensors")
    other = L1ChunkPolicy(L1ChunkConfig(**{**TINY, "d_model": 48, "n_layers": 3}))
    with pytest.raises(ValueError) as err:
        load_policy_weights(other, path)
    msg = str(err.value)
    assert "backbone.layers.2.attn.q_proj.weight" in msg  # missing
    assert "language.embed.weight" in msg and "shape" in msg
    assert "d_model" in msg


def test_bad_configs_name_the_field():
    with pytest.raises(ValidationError, match="divisible by n_heads"):
        L1ChunkConfig(d_model=30, n_heads=4)
    with pytest.raises(ValidationError, match="image_size"):
        L1ChunkConfig(obs_mode="pixels", image_size=40, stem_channels=[8, 8, 8, 8])
    with pytest.raises(ValidationError, match="d_model"):
        L1ChunkConfig(d_model=0)
    with pytest.raises(ValidationError, match="stem_channels"):
        L1ChunkConfig(stem_channels=[])
    with pytest.raises(ValidationError, match="integration_steps"):
        FlowConfig(integration_steps=0)


@pytest.mark.parametrize("policy_type", TYPES)
def test_predict_returns_clipped_env_actions_deterministically(policy_type):
    model = build_policy({"type": policy_type, **TINY}, "cpu")
    model.normalizer.set_stats(
        {
            "state": (torch.zeros(39), torch.ones(39)),
            "proprio": (torch.zeros(4), torch.ones(4)),
            "action": (torch.zeros(4), torch.full((4,), 100.0)),
        }
    )
    obs = {"state": np.random.randn(3, 39).astype(np.float32), "proprio": np.zeros((3, 4), np.float32)}
    out = model.predict_action_chunk(obs, ["reach-v3", "door-open-v3", "reach-v3"])
    assert out.shape == (3, 3, 4) and out.dtype == np.float32
    assert np.abs(out).max() <= 1.0
    assert model.training  # prediction restores the mode
    # the same observation gives the same chunk alone or in a batch (flow: fixed inference noise)
    alone = model.predict_action_chunk({k: v[1:2] for k, v in obs.items()}, ["door-open-v3"])
    assert np.allclose(alone[0], out[1], atol=1e-3)  # batched matmuls round differently (x100 std)
    with pytest.raises(ValueError, match="no instruction"):
        model.predict_action_chunk(obs, ["nope-v3"] * 3)


def test_flow_inference_integrates_its_velocity():
    """With a velocity that is constant, Euler integration from the noise lands exactly at noise - v."""
    model = FlowPolicy(FlowConfig(**TINY, integration_steps=4)).eval()
    with torch.no_grad():
        model.action_head.proj.weight.zero_()
        model.action_head.proj.bias.copy_(torch.tensor([0.5, -0.25, 0.0, 1.0]))
    b = batch(model.config, 2)
    generator = torch.Generator().manual_seed(model.config.inference_seed)
    noise = torch.randn(model.config.chunk_size, 4, generator=generator)
    expected = noise - torch.tensor([0.5, -0.25, 0.0, 1.0])
    assert torch.allclose(model.sample_actions(b), expected.expand(2, -1, -1), atol=1e-6)


def test_tokenizer_is_deterministic_and_padded():
    ids = tokenizer.encode("Open the DOOR, please!", vocab_size=1000, max_length=6)
    assert ids == tokenizer.encode("open the door please", vocab_size=1000, max_length=6)
    assert ids[4:] == [0, 0] and all(0 < i < 1000 for i in ids[:4])
    # crc32-based: fixed across processes and Python hash seeds
    assert ids[0] == 1 + __import__("zlib").crc32(b"open") % 999
    assert len(tokenizer.encode("a b c d e f g h", 50, 3)) == 3


def test_saved_file_is_byte_identical_across_processes(tmp_path):
    """Content-addressed artifacts need reproducible bytes (safetensors orders metadata randomly)."""
    import hashlib
    import subprocess
    import sys

    script = (
        "import sys, torch; from capvector.core.policies.base import build_policy, save_policy\n"
        "torch.manual_seed(0); m = build_policy({'d_model': 16, 'n_layers': 1, 'n_heads': 2}, 'cpu')\n"
        "save_policy(m, sys.argv[1], {'b': '1', 'a': '2', 'c': '3'})\n"
    )
    digests = set()
    for i in range(3):
        out = tmp_path / f"m{i}.safetensors"
        subprocess.run([sys.executable, "-c", script, str(out)], check=True)
        digests.add(hashlib.sha256(out.read_bytes()).hexdigest())
    assert len(digests) == 1


@pytest.mark.parametrize("policy_type,dropout", [("flow", 0.0), ("flow", 0.2), ("l1_chunk", 0.2)])
def test_the_loss_draws_from_the_policy_generator_not_the_global_rng(policy_type, dropout):
    """Flow matching's noise and times and the dropout masks come from `policy.generator` when one is
    set (the trainer sets one per run), so whatever else draws from torch's global RNG in between
    leaves the loss as it is; without one they come from the global RNG, as before."""
    torch.manual_seed(0)
    policy = fitted(build_policy({"type": policy_type, "dropout": dropout, **TINY}, "cpu")).train()
    b = batch(policy.config, 8)

    def loss(generator_seed, global_seed):
        policy.set_generator(
            None if generator_seed is None else torch.Generator().manual_seed(generator_seed)
        )
        torch.manual_seed(global_seed)
        return policy.compute_loss(b).loss

    assert policy.generator is None  # the default: torch's global RNG
    assert torch.equal(loss(5, global_seed=1), loss(5, global_seed=2))
    assert not torch.equal(loss(5, global_seed=1), loss(6, global_seed=1))
    assert torch.equal(loss(None, global_seed=1), loss(None, global_seed=1))
    assert not torch.equal(loss(None, global_seed=1), loss(None, global_seed=2))
    policy.set_generator(None)
    assert policy.generator is None


def test_flow_without_a_generator_draws_as_torch_distributions_beta_does():
    """The global-RNG path (held-out losses) draws τ and ε exactly as before policies had generators."""
    torch.manual_seed(0)
    policy = build_policy({"type": "flow", **TINY}, "cpu")
    actions = torch.zeros(16, TINY["chunk_size"], 4)
    torch.manual_seed(3)
    t, noise = policy.sample_time_and_noise(actions)
    torch.manual_seed(3)
    beta = torch.distributions.Beta(torch.tensor(1.5), torch.tensor(1.0)).sample((16,))
    assert torch.equal(t, beta * 0.999 + 0.001) and torch.equal(noise, torch.randn_like(actions))
