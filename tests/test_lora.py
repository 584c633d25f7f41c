"""LoRA (peft's layers) on a small transformer stand-in: forward, save (peft layout), load, exact merge."""

import json
import re

import pytest
import torch
from safetensors.torch import load_file
from torch import nn

from capvector_core.lora import (
    LoraConfig,
    adapter_modules,
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
        for m in adapter_modules(model).values():
            m.lora_B["default"].weight.normal_(std=0.1)


def test_apply_forward_and_pattern_errors():
    torch.manual_seed(0)
    model = TinyPolicy()
    x = torch.randn(3, 5, 10)
    before = model(x)
    names = apply_lora(model, LoraConfig(target_modules=["linear1", "linear2", "action_head"], r=4))
    assert "encoder.layers.0.linear1" in names and "encoder.layers.1.linear2" in names
    assert len(names) == 5 and set(adapter_modules(model)) == set(names)
    torch.testing.assert_close(model(x), before)  # B = 0 at init
    n_adapter = sum(4 * (m.in_features + m.out_features) for n, m in model.named_modules() if n in names)
    assert trainable_parameter_count(model) == n_adapter
    with pytest.raises(ValueError, match="'nothing', 'in_proj'"):
        apply_lora(TinyPolicy(), LoraConfig(target_modules=["linear1", "nothing", "in_proj"]))
    with pytest.raises(ValueError, match="already has adapters"):
        apply_lora(model, LoraConfig(target_modules=["embed"]))


def test_mha_children_refused():
    """nn.MultiheadAttention reads out_proj.weight without calling it: a peft layer there would never act."""
    model = TinyPolicy()
    with pytest.raises(ValueError, match="MultiheadAttention"):
        apply_lora(model, LoraConfig(target_modules=["out_proj"]))
    assert not adapter_modules(model) and trainable_parameter_count(model) == sum(
        p.numel() for p in model.parameters()
    )


@pytest.mark.parametrize("train_mode", [True, False])
def test_adapter_changes_output_also_through_fused_path(train_mode):
    torch.manual_seed(0)
    model = TinyPolicy()
    x = torch.randn(2, 5, 10)
    model.train(train_mode)
    with torch.no_grad():
        base = model(x)
    apply_lora(model, LoraConfig(target_modules=["linear1", "linear2"], r=4))
    _randomize_b(model)
    model.train(train_mode)
    with torch.no_grad():  # in eval mode, nn.TransformerEncoderLayer's fused path reads `.weight`
        adapted = model(x)
    assert not torch.allclose(adapted, base, atol=1e-4)
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
    names = apply_lora(model, config)
    _randomize_b(model)
    out = save_adapter(model, tmp_path / "adapter")
    doc = json.loads((out / "adapter_config.json").read_text())
    assert doc["peft_type"] == "LORA" and doc["r"] == 2 and doc["lora_alpha"] == 8 and doc["bias"] == "none"
    assert doc["rank_pattern"] == {} and doc["use_rslora"] is False and doc["inference_mode"] is True
    # peft full-matches a string target_modules against module names: it must pick exactly our layers
    assert isinstance(doc["target_modules"], str)
    assert [n for n, _ in TinyPolicy().named_modules() if re.fullmatch(doc["target_modules"], n)] == names
    keys = set(load_file(out / "adapter_model.safetensors"))
    assert "base_model.model.encoder.layers.0.linear1.lora_A.weight" in keys
    assert "base_model.model.action_head.lora_B.weight" in keys and len(keys) == 10

    fresh = TinyPolicy()
    fresh.load_state_dict(base_state)
    assert load_adapter(fresh, out) == names
    assert trainable_parameter_count(fresh) == trainable_parameter_count(model)
    x = torch.randn(2, 5, 10)
    torch.testing.assert_close(fresh(x), model(x))
    merge_lora(fresh)
    assert set(fresh.state_dict()) == set(base_state)  # original keys: vectors can be taken from it
    assert not adapter_modules(fresh) and not hasattr(fresh, "peft_config")
    torch.testing.assert_close(fresh(x), model(x), rtol=1e-5, atol=1e-5)
    m = model.encoder.layers[0].linear1
    ba = m.lora_B["default"].weight @ m.lora_A["default"].weight
    want = base_state["encoder.layers.0.linear1.weight"] + 4.0 * ba
    torch.testing.assert_close(fresh.state_dict()["encoder.layers.0.linear1.weight"], want.detach())
    assert all(p.requires_grad for p in fresh.parameters())


def test_rslora_scaling():
    torch.manual_seed(0)
    model = TinyPolicy()
    config = LoraConfig(target_modules=["action_head"], r=4, alpha=8, use_rslora=True)
    apply_lora(model, config)
    assert config.scaling == pytest.approx(4.0)
    assert model.action_head.scaling["default"] == pytest.approx(config.scaling)


def test_older_adapter_with_glob_targets_loads(tmp_path):
    """Adapters saved before peft was used list our glob patterns, which peft cannot read; we still can."""
    torch.manual_seed(0)
    model = TinyPolicy()
    base_state = {k: v.clone() for k, v in model.state_dict().items()}
    apply_lora(model, LoraConfig(target_modules=["encoder.layers.*.linear*"], r=2))
    _randomize_b(model)
    out = save_adapter(model, tmp_path / "a")
    doc = json.loads((out / "adapter_config.json").read_text())
    doc["target_modules"] = ["encoder.layers.*.linear*"]
    (out / "adapter_config.json").write_text(json.dumps(doc))
    fresh = TinyPolicy()
    fresh.load_state_dict(base_state)
    load_adapter(fresh, out)
    x = torch.randn(2, 5, 10)
    torch.testing.assert_close(fresh(x), model(x))


def test_load_into_mismatched_model_fails(tmp_path):
    model = TinyPolicy(d=32)
    apply_lora(model, LoraConfig(target_modules=["action_head"], r=2))
    save_adapter(model, tmp_path / "a")
    other = TinyPolicy(d=16)
    with pytest.raises(ValueError, match="shapes"):
        load_adapter(other, tmp_path / "a")
    assert not adapter_modules(other) and not hasattr(other, "peft_config")  # left as it was
    assert all(p.requires_grad for p in other.parameters())
    with pytest.raises(FileExistsError):
        save_adapter(model, tmp_path / "a")


def test_other_peft_types_refused_by_name(tmp_path):
    model = TinyPolicy()
    apply_lora(model, LoraConfig(target_modules=["action_head"], r=2))
    out = save_adapter(model, tmp_path / "a")
    doc = json.loads((out / "adapter_config.json").read_text())
    for kind, hint in (("LOHA", "LOHA"), ("LORA_SP", "lora_sp.load_adapter")):
        (out / "adapter_config.json").write_text(json.dumps({**doc, "peft_type": kind}))
        with pytest.raises(ValueError, match=hint):
            load_adapter(TinyPolicy(), out)
