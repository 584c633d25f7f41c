"""The orthogonal regularizer's value and gradient against hand computations (dense, LoRA exact, A-only)."""

import pytest
import torch
from torch import nn

from capvector_core.lora import LoraConfig, apply_lora
from capvector_core.orthogonal import OrthogonalRegularizer
from capvector_core.safetensors_io import write_checkpoint


def _model():
    torch.manual_seed(0)
    return nn.Sequential(nn.Linear(8, 16), nn.ReLU(), nn.Linear(16, 4))


def test_dense_value_and_gradient(tmp_path):
    model = _model()
    meta = {k: v.detach().clone() for k, v in model.state_dict().items()}
    gamma = {k: torch.randn_like(v) for k, v in meta.items()}
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1 * torch.randn_like(p))
    reg = OrthogonalRegularizer(model, gamma, meta, weight=1e-2, exclude=["2.bias"])
    loss = reg(model)
    params = dict(model.named_parameters())
    used = ["0.weight", "0.bias", "2.weight"]
    want = 1e-2 * sum((gamma[n] * (params[n] - meta[n])).abs().sum() for n in used)
    torch.testing.assert_close(loss, want.detach())
    loss.backward()
    for n in used:
        hand = 1e-2 * gamma[n].abs() * torch.sign(params[n].detach() - meta[n])
        torch.testing.assert_close(params[n].grad, hand)
    assert params["2.bias"].grad is None
    # from safetensors files, as the pipeline passes them
    write_checkpoint(tmp_path / "g.safetensors", gamma)
    write_checkpoint(tmp_path / "m.safetensors", meta)
    reg2 = OrthogonalRegularizer(
        model, tmp_path / "g.safetensors", tmp_path / "m.safetensors", weight=1e-2, exclude=["2.bias"]
    )
    torch.testing.assert_close(reg2(model), want.detach())


def test_dense_zero_at_start_and_skips_frozen():
    model = _model()
    meta = {k: v.detach().clone() for k, v in model.state_dict().items()}
    gamma = {k: torch.randn_like(v) for k, v in meta.items()}
    model[0].weight.requires_grad_(False)
    reg = OrthogonalRegularizer(model, gamma, meta)
    assert "0.weight" not in reg.names and float(reg(model).detach()) == 0.0
    with pytest.raises(ValueError, match="no trainable parameter"):
        OrthogonalRegularizer(model, {"other.weight": torch.zeros(1)}, meta)
    with pytest.raises(ValueError, match="needs θ_meta"):
        OrthogonalRegularizer(model, gamma)


def test_lora_exact_and_a_only():
    model = _model()
    gamma = {k: torch.randn_like(v) for k, v in model.state_dict().items()}
    apply_lora(model, LoraConfig(target_modules=["0", "2"], r=3, alpha=6))
    with torch.no_grad():
        for m in (model[0], model[2]):
            m.lora_B.weight.normal_()
    exact = OrthogonalRegularizer(model, gamma, mode="lora_exact", weight=0.5)
    a_only = OrthogonalRegularizer(model, gamma, mode="lora_a", weight=0.5)
    want_exact = sum(
        (gamma[f"{i}.weight"] * (2.0 * m.lora_B.weight @ m.lora_A.weight)).abs().sum()
        for i, m in ((0, model[0]), (2, model[2]))
    )
    want_a = sum(
        (gamma[f"{i}.weight"] @ m.lora_A.weight.T).abs().sum() for i, m in ((0, model[0]), (2, model[2]))
    )
    torch.testing.assert_close(exact(model), 0.5 * want_exact.detach())
    loss = a_only(model)
    torch.testing.assert_close(loss, 0.5 * want_a.detach())
    loss.backward()
    a = model[0].lora_A.weight
    hand = 0.5 * torch.sign(gamma["0.weight"] @ a.detach().T).T @ gamma["0.weight"]
    torch.testing.assert_close(a.grad, hand)
    assert model[0].lora_B.weight.grad is None  # the A-only form is independent of B


def test_a_only_zero_means_orthogonal_for_every_b():
    lin = nn.Linear(6, 5)
    model = nn.Sequential(lin)
    apply_lora(model, LoraConfig(target_modules=["0"], r=2))
    g = torch.zeros(5, 6)
    g[:, :3] = torch.randn(5, 3)  # γ's rows live in the first three input coordinates
    with torch.no_grad():
        model[0].lora_A.weight.zero_()
        model[0].lora_A.weight[:, 3:] = torch.randn(2, 3)  # A reads only the other coordinates
        model[0].lora_B.weight.normal_()
    reg = OrthogonalRegularizer(model, {"0.weight": g}, mode="lora_a")
    assert float(reg(model).detach()) == 0.0
    assert abs(float((g * model[0].delta_weight().detach()).sum())) < 1e-6
