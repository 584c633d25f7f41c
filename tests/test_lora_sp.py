"""LoRA-SP: energy-based selection, losses, active ranks, save/load, and the dense merge."""

import json

import pytest
import torch
from safetensors.torch import load_file
from torch import nn

from capvector.core.adapters import lora
from capvector.core.adapters.lora import merge_lora, trainable_parameter_count
from capvector.core.adapters.lora_sp import (
    LoraSPConfig,
    active_ranks,
    apply_lora_sp,
    calibrate,
    load_adapter,
    lora_sp_loss,
    save_adapter,
    select_active,
)


class TinyPolicy(nn.Module):
    def __init__(self, d=32):
        super().__init__()
        self.embed = nn.Linear(10, d)
        layer = nn.TransformerEncoderLayer(d, 4, 64, dropout=0.0, batch_first=True)
        self.encoder = nn.TransformerEncoder(layer, 2, enable_nested_tensor=False)
        self.action_head = nn.Linear(d, 4)

    def forward(self, x):
        return self.action_head(self.encoder(self.embed(x)))


def _energy(scores, mask):
    return (scores.square() * mask).sum(-1) / scores.square().sum(-1)


@pytest.mark.parametrize("eta", [0.3, 0.5, 0.9, 0.99])
def test_selection_is_smallest_k_reaching_eta(eta):
    torch.manual_seed(0)
    s = torch.rand(500, 16) ** 3
    mask, k = select_active(s, eta)
    assert torch.equal(mask.sum(-1), k)
    assert bool((_energy(s, mask) >= eta - 1e-6).all())
    top = s.sort(-1, descending=True).values
    prev = top.square().cumsum(-1).gather(-1, (k - 2).clamp(min=0).unsqueeze(-1)).squeeze(
        -1
    ) / s.square().sum(-1)
    assert bool(((prev < eta) | (k == 1)).all())  # k − 1 would not reach η
    kept_min = torch.where(mask, s, torch.inf).min(-1).values
    dropped_max = torch.where(mask, -torch.inf, s).max(-1).values
    assert bool((kept_min >= dropped_max).all())  # the kept scores are the largest ones


def test_eta_one_keeps_whole_bank():
    s = torch.tensor([[1.0, 1e-6, 1e-7, 0.5]])
    mask, k = select_active(s, 1.0)
    assert bool(mask.all()) and int(k) == 4


def test_forward_losses_ranks_and_gradients():
    torch.manual_seed(0)
    model = TinyPolicy()
    cfg = LoraSPConfig(target_modules=["linear1", "linear2"], bank_size=16, alpha=32, eta=0.9)
    names = apply_lora_sp(model, cfg)
    assert len(names) == 4
    assert trainable_parameter_count(model) == sum(
        16 * (m.in_features + m.out_features) + 16 * m.in_features + 16
        for n, m in model.named_modules()
        if n in names
    )
    x = torch.randn(4, 6, 10)
    before = model(x)
    loss = lora_sp_loss(model)
    mods = [model.get_submodule(n) for n in names]
    spec = torch.stack([m.last_losses["spectral"] for m in mods]).mean()
    router = torch.stack([m.last_losses["router"] for m in mods]).mean()
    torch.testing.assert_close(loss, 1e-2 * spec + 1e-3 * router)
    assert 0.0 <= float(spec.detach()) <= 0.1 + 1e-6  # E(k) ≥ η = 0.9 for every token
    (before.square().mean() + loss).backward()
    assert mods[0].lora_router.weight.grad is not None and mods[0].lora_A.weight.grad is not None
    ranks = active_ranks(model)
    assert set(ranks) == set(names) and all(1 <= r <= 16 for r in ranks.values())


def test_mha_children_refused():
    with pytest.raises(ValueError, match="MultiheadAttention"):
        apply_lora_sp(TinyPolicy(), LoraSPConfig(target_modules=["out_proj"], bank_size=4))


def test_merge_exact_when_scores_input_independent(tmp_path):
    torch.manual_seed(0)
    model = TinyPolicy()
    apply_lora_sp(model, LoraSPConfig(target_modules=["linear1", "action_head"], bank_size=8, eta=0.7))
    with torch.no_grad():
        for m in model.modules():
            if hasattr(m, "lora_router"):
                m.lora_router.weight.zero_()
                m.lora_router.bias.normal_()
                m.lora_B.weight.normal_(std=0.1)
    model.eval()
    x = torch.randn(2, 5, 10)
    with torch.no_grad():
        adapted = model(x)
    merged = merge_lora(model)
    with torch.no_grad():
        torch.testing.assert_close(merged(x), adapted, rtol=1e-5, atol=1e-5)


def test_input_dependent_merge_needs_calibration_and_uses_mean_scores():
    torch.manual_seed(0)
    model = nn.Sequential(nn.Linear(6, 5))
    apply_lora_sp(model, LoraSPConfig(target_modules=["0"], bank_size=4, eta=0.8))
    m = model[0]
    with torch.no_grad():
        m.lora_B.weight.normal_()
    with pytest.raises(RuntimeError, match="calibrate"):
        m.delta_weight()
    batches = [torch.randn(7, 6) for _ in range(3)]
    calibrate(model, batches)
    xs = torch.cat(batches)
    _, s = m.scores(xs)
    mask, k = select_active(s, 0.8)
    torch.testing.assert_close(m.merge_scores(), (s * mask).mean(0).detach())
    assert m.mean_active_rank == pytest.approx(k.double().mean().item())


def test_save_load_round_trip_with_rank_pattern(tmp_path):
    torch.manual_seed(0)
    model = TinyPolicy()
    base_state = {k: v.clone() for k, v in model.state_dict().items()}
    cfg = LoraSPConfig(target_modules=["linear1"], bank_size=8, alpha=16, eta=0.9)
    apply_lora_sp(model, cfg)
    with torch.no_grad():
        for m in model.modules():
            if hasattr(m, "lora_router"):
                m.lora_B.weight.normal_(std=0.1)
    x = torch.randn(2, 5, 10)
    model.train()
    model(x)
    calibrate(model, [x])
    out = save_adapter(model, tmp_path / "sp")
    doc = json.loads((out / "adapter_config.json").read_text())
    assert doc["peft_type"] == "LORA_SP" and doc["r"] == 8 and doc["lora_alpha"] == 16
    assert isinstance(doc["target_modules"], str)  # the peft regex of the patterns, as for LoRA
    keys = set(load_file(out / "adapter_model.safetensors"))
    assert "base_model.model.encoder.layers.0.linear1.lora_router.weight" in keys
    assert "base_model.model.encoder.layers.1.linear1.lora_stats.score_sum" in keys and len(keys) == 14
    assert set(doc["rank_pattern"]) == {"encoder.layers.0.linear1", "encoder.layers.1.linear1"}
    assert all(1 <= v <= 8 for v in doc["rank_pattern"].values())
    fresh = TinyPolicy()
    fresh.load_state_dict(base_state)
    load_adapter(fresh, out)
    model.eval()
    fresh.eval()
    with torch.no_grad():
        torch.testing.assert_close(fresh(x), model(x))
    torch.testing.assert_close(
        fresh.encoder.layers[0].linear1.merge_scores(), model.encoder.layers[0].linear1.merge_scores()
    )


def test_older_file_with_pattern_list_loads_and_peft_savers_refuse(tmp_path):
    torch.manual_seed(0)
    model = TinyPolicy()
    base_state = {k: v.clone() for k, v in model.state_dict().items()}
    apply_lora_sp(model, LoraSPConfig(target_modules=["encoder.layers.*.linear1"], bank_size=4))
    assert not lora.adapter_modules(model)  # LoRA-SP layers are ours, not peft's
    with pytest.raises(TypeError, match="save_adapter"):
        lora.save_adapter(model, tmp_path / "x")
    x = torch.randn(2, 5, 10)
    calibrate(model, [x])
    out = save_adapter(model, tmp_path / "sp")
    doc = json.loads((out / "adapter_config.json").read_text())
    doc["target_modules"] = ["encoder.layers.*.linear1"]  # as files written before the peft regex
    (out / "adapter_config.json").write_text(json.dumps(doc))
    fresh = TinyPolicy()
    fresh.load_state_dict(base_state)
    assert load_adapter(fresh, out) == ["encoder.layers.0.linear1", "encoder.layers.1.linear1"]
    with pytest.raises(ValueError, match="lora_sp.load_adapter"):
        lora.load_adapter(TinyPolicy(), out)
    model.eval()
    fresh.eval()
    with torch.no_grad():
        torch.testing.assert_close(fresh(x), model(x))
