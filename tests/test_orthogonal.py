"""The orthogonal regularizer vs hand computations (dense; exact and A-only on peft and LoRA-SP layers)."""

import peft
import pytest
import torch
from peft.tuners.lora import LoraLayer
from torch import nn

from capvector.core.adapters.lora import LoraConfig, apply_lora, delta_weight, load_adapter
from capvector.core.adapters.lora_sp import LoraSPConfig, apply_lora_sp
from capvector.core.training.orthogonal import OrthogonalRegularizer
from capvector.core.vectors.safetensors_io import write_checkpoint


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
    reg = OrthogonalRegularizer(model, gamma, meta, lambda_absolute=1e-2, exclude=["2.bias"])
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
        model,
        tmp_path / "g.safetensors",
        tmp_path / "m.safetensors",
        lambda_absolute=1e-2,
        exclude=["2.bias"],
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


def _ab(m):
    return m.lora_A["default"].weight, m.lora_B["default"].weight


def test_lora_exact_and_a_only():
    model = _model()
    gamma = {k: torch.randn_like(v) for k, v in model.state_dict().items()}
    apply_lora(model, LoraConfig(target_modules=["0", "2"], r=3, alpha=6))
    with torch.no_grad():
        for m in (model[0], model[2]):
            _ab(m)[1].normal_()
    exact = OrthogonalRegularizer(model, gamma, mode="lora_exact", lambda_absolute=0.5)
    a_only = OrthogonalRegularizer(model, gamma, mode="lora_a", lambda_absolute=0.5)
    want_exact = sum(
        (gamma[f"{i}.weight"] * (2.0 * _ab(m)[1] @ _ab(m)[0])).abs().sum()
        for i, m in ((0, model[0]), (2, model[2]))
    )
    want_a = sum((gamma[f"{i}.weight"] @ _ab(m)[0].T).abs().sum() for i, m in ((0, model[0]), (2, model[2])))
    loss_exact = exact(model)
    torch.testing.assert_close(loss_exact, 0.5 * want_exact.detach())
    loss_exact.backward()  # gradient reaches both A and B of peft's layers, as computed by hand
    a, b = _ab(model[0])
    g = gamma["0.weight"]
    sign = torch.sign(g * (2.0 * b.detach() @ a.detach())) * g
    torch.testing.assert_close(b.grad, 0.5 * 2.0 * sign @ a.detach().T)
    torch.testing.assert_close(a.grad, 0.5 * 2.0 * b.detach().T @ sign)
    model.zero_grad(set_to_none=True)
    loss = a_only(model)
    torch.testing.assert_close(loss, 0.5 * want_a.detach())
    loss.backward()
    hand = 0.5 * torch.sign(g @ a.detach().T).T @ g
    torch.testing.assert_close(a.grad, hand)
    assert b.grad is None  # the A-only form is independent of B


def test_lora_exact_uses_peft_scaling_of_a_peft_made_adapter(tmp_path):
    """rsLoRA and alpha_pattern/rank_pattern from a peft adapter give each layer its own s."""
    base = _model()
    gamma = {k: torch.randn_like(v) for k, v in base.state_dict().items()}
    state = {k: v.clone() for k, v in base.state_dict().items()}
    config = peft.LoraConfig(
        target_modules=["0", "2"],
        r=4,
        lora_alpha=8,
        use_rslora=True,
        rank_pattern={"2": 2},
        alpha_pattern={"2": 3},
    )
    made = peft.get_peft_model(base, config)
    with torch.no_grad():
        for m in made.modules():
            if isinstance(m, LoraLayer):
                m.lora_B["default"].weight.normal_()
    made.save_pretrained(tmp_path / "peft")
    model = _model()
    model.load_state_dict(state)
    load_adapter(model, tmp_path / "peft")
    reg = OrthogonalRegularizer(model, gamma, mode="lora_exact", lambda_absolute=0.1)
    scales = {0: 8 / 4**0.5, 2: 3 / 2**0.5}
    want = sum(
        (gamma[f"{i}.weight"] * (scales[i] * _ab(model[i])[1] @ _ab(model[i])[0])).abs().sum() for i in (0, 2)
    )
    torch.testing.assert_close(reg(model), 0.1 * want.detach())


def test_lora_sp_layers():
    """LoRA-SP: exact ΔW = s·B·diag(σ)·A (constant scores here) and the A-only form on its A."""
    model = _model()
    gamma = {k: torch.randn_like(v) for k, v in model.state_dict().items()}
    apply_lora_sp(model, LoraSPConfig(target_modules=["0"], bank_size=4, alpha=8, eta=1.0))
    m = model[0]
    with torch.no_grad():
        m.lora_router.weight.zero_()
        m.lora_B.weight.normal_()
    sigma = torch.nn.functional.softplus(m.lora_router.bias.detach())
    want = (gamma["0.weight"] * (2.0 * (m.lora_B.weight * sigma) @ m.lora_A.weight)).abs().sum()
    exact = OrthogonalRegularizer(model, gamma, mode="lora_exact", lambda_absolute=0.5)
    loss = exact(model)
    torch.testing.assert_close(loss, 0.5 * want.detach())
    loss.backward()
    assert m.lora_A.weight.grad is not None and m.lora_B.weight.grad is not None
    a_only = OrthogonalRegularizer(model, gamma, mode="lora_a", lambda_absolute=0.5)
    torch.testing.assert_close(
        a_only(model), 0.5 * (gamma["0.weight"] @ m.lora_A.weight.T).abs().sum().detach()
    )


def test_a_only_zero_means_orthogonal_for_every_b():
    lin = nn.Linear(6, 5)
    model = nn.Sequential(lin)
    apply_lora(model, LoraConfig(target_modules=["0"], r=2))
    g = torch.zeros(5, 6)
    g[:, :3] = torch.randn(5, 3)  # γ's rows live in the first three input coordinates
    a, b = _ab(model[0])
    with torch.no_grad():
        a.zero_()
        a[:, 3:] = torch.randn(2, 3)  # A reads only the other coordinates
        b.normal_()
    reg = OrthogonalRegularizer(model, {"0.weight": g}, mode="lora_a")
    assert float(reg(model).detach()) == 0.0
    assert abs(float((g * delta_weight(model[0]).detach()).sum())) < 1e-6


def test_filters_use_the_pattern_syntax():
    model = _model()
    meta = {k: v.detach().clone() for k, v in model.state_dict().items()}
    gamma = {k: torch.randn_like(v) for k, v in meta.items()}
    assert OrthogonalRegularizer(model, gamma, meta, include=["weight"]).names == ["0.weight", "2.weight"]
    with pytest.raises(ValueError, match="'nothing'"):
        OrthogonalRegularizer(model, gamma, meta, include=["weight", "nothing"])


def test_dora_refused():
    model = _model()
    gamma = {k: torch.randn_like(v) for k, v in model.state_dict().items()}
    peft.inject_adapter_in_model(peft.LoraConfig(target_modules=["0"], r=2, use_dora=True), model)
    with pytest.raises(ValueError, match="DoRA"):
        OrthogonalRegularizer(model, gamma, mode="lora_exact")


def test_dense_fused_equals_per_tensor_reference():
    """The one-node dense loss (foreach forward, hand-written backward) vs the per-tensor autograd graph:
    same value and gradients, bit for bit, with a zero-γ tensor, a frozen one and an SFT-like loss beside."""
    torch.manual_seed(1)
    model = nn.Sequential(nn.Embedding(10, 6), nn.Linear(6, 12), nn.LayerNorm(12), nn.Linear(12, 3))
    meta = {k: v.detach().clone() for k, v in model.state_dict().items()}
    gamma = {k: 1e-3 * torch.randn_like(v) for k, v in meta.items()}
    gamma["2.weight"].zero_()  # γ zero everywhere: no arithmetic, a zero gradient all the same
    gamma["1.bias"][:5] = 0.0
    with torch.no_grad():
        for p in model.parameters():
            p.add_(1e-2 * torch.randn_like(p))
        model[1].bias[:3] = meta["1.bias"][:3]  # Δ exactly 0: sign 0
    model[3].bias.requires_grad_(False)
    reg = OrthogonalRegularizer(model, gamma, meta, lambda_absolute=0.3)
    params = dict(model.named_parameters())
    assert reg.names == [n for n in params if n != "3.bias"]

    def grads(loss_fn):
        for p in model.parameters():
            p.grad = None
        x = torch.tensor([[1, 2, 3], [4, 5, 9]])
        task = model(x).square().mean()  # an SFT-like loss: the gradients add up on the same tensors
        loss = loss_fn()
        (task + loss).backward()
        return loss.detach(), {n: None if p.grad is None else p.grad.clone() for n, p in params.items()}

    def reference():
        terms = [
            torch.linalg.vector_norm(torch.sub(params[n], meta[n]).mul_(gamma[n]), 1, dtype=torch.float32)
            for n in reg.names
        ]
        return torch.stack(terms).sum() * 0.3

    got_loss, got = grads(lambda: reg(model))
    want_loss, want = grads(reference)
    torch.testing.assert_close(got_loss, want_loss, rtol=1e-6, atol=0)  # the sum may skip γ=0's zero term
    assert set(got) == set(want) and got["3.bias"] is None and want["3.bias"] is None
    for n in reg.names:
        assert torch.equal(got[n], want[n]), n
    # the regularizer alone: the zero-γ tensor still gets an all-zero gradient (not None), as before
    for p in model.parameters():
        p.grad = None
    reg(model).backward()
    assert torch.equal(params["2.weight"].grad, torch.zeros_like(params["2.weight"]))
    # without a zero-γ tensor the value is bit for bit the per-tensor one
    gamma["2.weight"].normal_()
    reg = OrthogonalRegularizer(model, gamma, meta, lambda_absolute=0.3)
    assert torch.equal(reg(model).detach(), reference().detach())
    with torch.no_grad():  # evaluation only: no graph, same value
        assert torch.equal(reg(model), reference())
    # a λ changed after construction (tasks/steps/training.py scales it) is the one used, forward and backward
    reg.lambda_absolute = 0.05
    for p in model.parameters():
        p.grad = None
    reg(model).backward()
    hand = 0.05 * gamma["0.weight"].abs() * torch.sign(params["0.weight"].detach() - meta["0.weight"])
    torch.testing.assert_close(params["0.weight"].grad, hand)
