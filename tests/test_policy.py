"""Policy: shapes in both modes, stable names, exact save/load, config mismatch, tokenizer."""

import numpy as np
import pytest
import torch
from pydantic import ValidationError

from capvector_core import tokenizer
from capvector_core.policy import (
    CONFIG_METADATA_KEY,
    PolicyConfig,
    VLAPolicy,
    load_policy,
    load_policy_weights,
    read_metadata,
    save_policy,
)

TINY = dict(d_model=32, n_layers=2, n_heads=4, chunk_size=3, vocab_size=64, max_instruction_tokens=6)


def batch(config: PolicyConfig, b: int = 5) -> dict:
    return {
        "tokens": tokenizer.encode_batch(
            ["open the door"] * b, config.vocab_size, config.max_instruction_tokens
        ),
        "state": torch.randn(b, 39),
        "proprio": torch.randn(b, 4),
        "image": torch.randint(0, 256, (b, config.image_size, config.image_size, 3), dtype=torch.uint8),
    }


@pytest.mark.parametrize("mode,n_obs", [("state", 5), ("pixels", 4)])
def test_forward_shapes(mode, n_obs):
    config = PolicyConfig(obs_mode=mode, image_size=32, stem_channels=[8, 8, 8, 8], **TINY)
    out = VLAPolicy(config)(batch(config))
    assert out["actions"].shape == (5, 3, 4)
    assert len(out["hidden"]) == 2
    assert out["hidden"][0].shape == (5, config.n_tokens, 32)
    obs = out["token_slices"]["vision" if mode == "pixels" else "state"]
    assert obs.stop - obs.start == n_obs == config.n_obs_tokens


def test_parameter_names_are_stable():
    keys = set(VLAPolicy(PolicyConfig(**TINY)).state_dict())
    for key in [
        "language.embed.weight",
        "state.proj.hand.weight",
        "state.proj.goal.bias",
        "proprio.proj.weight",
        "embeddings.position",
        "embeddings.action_queries",
        "embeddings.token_type.weight",
        "backbone.layers.0.attn.q_proj.weight",
        "backbone.layers.1.attn.o_proj.bias",
        "backbone.layers.0.mlp.fc1.weight",
        "backbone.layers.0.norm1.weight",
        "backbone.norm.weight",
        "action_head.proj.weight",
        "normalizer.action_std",
        "normalizer.fitted",
    ]:
        assert key in keys, key
    pixels = set(VLAPolicy(PolicyConfig(obs_mode="pixels", image_size=32, **TINY)).state_dict())
    assert {"vision.stem.0.weight", "vision.proj.weight"} <= pixels
    assert not any(k.startswith("state.") for k in pixels)


def test_save_load_roundtrip_is_exact(tmp_path):
    config = PolicyConfig(obs_mode="pixels", image_size=32, **TINY)
    model = VLAPolicy(config)
    model.normalizer.set_stats(
        {k: (torch.randn(d), torch.rand(d) + 0.5) for k, d in [("state", 39), ("proprio", 4), ("action", 4)]}
    )
    path = save_policy(model, tmp_path / "p.safetensors", metadata={"note": "hi"})
    assert read_metadata(path)["note"] == "hi"
    assert PolicyConfig.model_validate_json(read_metadata(path)[CONFIG_METADATA_KEY]) == config
    loaded = load_policy(path, device="cpu")
    for k, v in model.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k]), k
    b = batch(config)
    assert torch.equal(model.eval()(b)["actions"], loaded.eval()(b)["actions"])


def test_config_mismatch_names_keys_and_shapes(tmp_path):
    path = save_policy(VLAPolicy(PolicyConfig(**TINY)), tmp_path / "p.safetensors")
    other = VLAPolicy(PolicyConfig(**{**TINY, "d_model": 48, "n_layers": 3}))
    with pytest.raises(ValueError) as err:
        load_policy_weights(other, path)
    msg = str(err.value)
    assert "backbone.layers.2.attn.q_proj.weight" in msg  # missing
    assert "language.embed.weight" in msg and "shape" in msg
    assert "d_model" in msg


def test_bad_configs_name_the_field():
    with pytest.raises(ValidationError, match="divisible by n_heads"):
        PolicyConfig(d_model=30, n_heads=4)
    with pytest.raises(ValidationError, match="image_size"):
        PolicyConfig(obs_mode="pixels", image_size=40, stem_channels=[8, 8, 8, 8])
    with pytest.raises(ValidationError, match="d_model"):
        PolicyConfig(d_model=0)
    with pytest.raises(ValidationError, match="stem_channels"):
        PolicyConfig(stem_channels=[])


def test_act_returns_clipped_env_actions():
    config = PolicyConfig(**TINY)
    model = VLAPolicy(config)
    model.normalizer.set_stats(
        {
            "state": (torch.zeros(39), torch.ones(39)),
            "proprio": (torch.zeros(4), torch.ones(4)),
            "action": (torch.zeros(4), torch.full((4,), 100.0)),
        }
    )
    obs = {"state": np.random.randn(3, 39).astype(np.float32), "proprio": np.zeros((3, 4), np.float32)}
    out = model.act(obs, ["reach-v3", "door-open-v3", "reach-v3"])
    assert out.shape == (3, 3, 4) and out.dtype == np.float32
    assert np.abs(out).max() <= 1.0
    assert model.training  # act restores the mode
    with pytest.raises(ValueError, match="no instruction"):
        model.act(obs, ["nope-v3"] * 3)


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
        "import sys, torch; from capvector_core.policy import PolicyConfig, build_policy, save_policy\n"
        "torch.manual_seed(0); m = build_policy(PolicyConfig(d_model=16, n_layers=1, n_heads=2), 'cpu')\n"
        "save_policy(m, sys.argv[1], {'b': '1', 'a': '2', 'c': '3'})\n"
    )
    digests = set()
    for i in range(3):
        out = tmp_path / f"m{i}.safetensors"
        subprocess.run([sys.executable, "-c", script, str(out)], check=True)
        digests.add(hashlib.sha256(out.read_bytes()).hexdigest())
    assert len(digests) == 1
