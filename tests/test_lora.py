"""LoRA on a small transformer policy stand-in: forward, save (peft layout), load, exact merge."""

import json

import pytest
import torch
from safetensors.torch import load_file
from torch import nn

from capvector_core.lora import (
    LoraConfig,
    apply_lora,
    load_adapter,
    merge_lora,
    save_adapter,
    trainable_parameter_count,
)


class TinyPolicy(nn.Module):
    """nn.TransformerEncoder + linear heads, shaped like a (very) small VLA."""

    def __init__(self, d=32):
        super().__init__()
        self.embed = nn.Linear(10, d)
        layer = nn.TransformerEncoderLayer(d, 4, 64, dropout=0.0, batch_first=True)
        self.encoder = nn.TransformerEncoder(layer, 2, enable_nested_tensor=False)
        self.action_head = nn.Linear(d, 4)

    def forward(self, x):
        return self.action_head(self.encoder(self.embed(x)))


def _randomize_b(model):
    with torch.no_grad():
        for m in model.modules():
            if hasattr(m, "lora_B"):
                m.lora_B.weight.normal_(std=0.1)


def test_apply_forward_and_pattern_errors():
    torch.manual_seed(0)
    model = TinyPolicy()
    x = torch.randn(3, 5, 10)
    before = model(x)
    names = apply_lora(
        model, LoraConfig(target_modules=["linear1", "linear2", "out_proj", "action_head"], r=4)
    )
    assert "encoder.layers.0.linear1" in names and "encoder.layers.1.self_attn.out_proj" in names
    assert len(names) == 7
    torch.testing.assert_close(model(x), before)  # B = 0 at init
    n_adapter = sum(4 * (m.in_features + m.out_features) for n, m in model.named_modules() if n in names)
    assert trainable_parameter_count(model) == n_adapter
    with pytest.raises(ValueError, match="'nothing', 'in_proj'"):
        apply_lora(TinyPolicy(), LoraConfig(target_modules=["linear1", "nothing", "in_proj"]))


@pytest.mark.parametrize("train_mode", [True, False])
def test_adapter_changes_output_also_through_mha_and_fused_path(train_mode):
    torch.manual_seed(0)
    model = TinyPolicy()
    apply_lora(model, LoraConfig(target_modules=["out_proj", "linear1"], r=4))
    _randomize_b(model)
    model.train(train_mode)
    x = torch.randn(2, 5, 10)
    with torch.no_grad():
        adapted = model(x)
    merged = merge_lora(model)
    merged.train(train_mode)
    with torch.no_grad():
        dense = merged(x)
    torch.testing.assert_close(adapted, dense, rtol=1e-5, atol=1e-5)


def test_save_load_merge_round_trip(tmp_path):
    torch.manual_seed(0)
    base = TinyPolicy()
    base_state = {k: v.clone() for k, v in base.state_dict().items()}
    model = TinyPolicy()
    model.load_state_dict(base_state)
    config = LoraConfig(target_modules=["encoder.layers.*.linear*", "action_head"], r=2, alpha=8)
    apply_lora(model, config)
    _randomize_b(model)
    out = save_adapter(model, tmp_path / "adapter")
    doc = json.loads((out / "adapter_config.json").read_text())
    assert doc["peft_type"] == "LORA" and doc["r"] == 2 and doc["lora_alpha"] == 8 and doc["bias"] == "none"
    assert doc["rank_pattern"] == {} and doc["target_modules"] == config.target_modules
    keys = set(load_file(out / "adapter_model.safetensors"))
    assert "base_model.model.encoder.layers.0.linear1.lora_A.weight" in keys
    assert "base_model.model.action_head.lora_B.weight" in keys and len(keys) == 10

    fresh = TinyPolicy()
    fresh.load_state_dict(base_state)
    load_adapter(fresh, out)
    x = torch.randn(2, 5, 10)
    torch.testing.assert_close(fresh(x), model(x))
    merge_lora(fresh)
    assert set(fresh.state_dict()) == set(base_state)  # original keys: vectors can be taken from it
    torch.testing.assert_close(fresh(x), model(x), rtol=1e-5, atol=1e-5)
    m = model.encoder.layers[0].linear1
    want = base_state["encoder.layers.0.linear1.weight"] + 4.0 * m.lora_B.weight @ m.lora_A.weight
    torch.testing.assert_close(fresh.state_dict()["encoder.layers.0.linear1.weight"], want.detach())
    assert all(p.requires_grad for p in fresh.parameters())


def test_load_into_mismatched_model_fails(tmp_path):
    model = TinyPolicy(d=32)
    apply_lora(model, LoraConfig(target_modules=["action_head"], r=2))
    save_adapter(model, tmp_path / "a")
    with pytest.raises(ValueError, match="shapes"):
        load_adapter(TinyPolicy(d=16), tmp_path / "a")
    with pytest.raises(FileExistsError):
        save_adapter(model, tmp_path / "a")
