"""Our LoRA adapters with real peft (no mocks), both ways, on a stand-in and on our policy.

(a) an adapter saved by `lora.save_adapter` loads with `peft.PeftModel.from_pretrained(policy, dir)`, gives
our outputs, and its `merge_and_unload()` equals our `merge_lora` tensor for tensor;
(b) an adapter made by peft (rsLoRA, alpha_pattern, rank_pattern) loads with `lora.load_adapter` and gives
peft's outputs (before peft, such an adapter loaded here with the wrong scaling).
"""

import copy

import peft
import pytest
import torch
from peft.tuners.lora import LoraLayer
from torch import nn
from torch.nn import functional as F

from capvector.core.adapters.lora import (
    LoraConfig,
    adapter_modules,
    apply_lora,
    load_adapter,
    merge_lora,
    save_adapter,
)
from capvector.core.policies.base import build_policy

TARGETS = ["attn.*_proj", "mlp.fc*", "action_head.*"]  # the pipeline's default LoRA targets


class Attention(nn.Module):
    def __init__(self, d):
        super().__init__()
        self.q_proj, self.k_proj, self.v_proj, self.o_proj = (nn.Linear(d, d) for _ in range(4))

    def forward(self, x):
        att = torch.softmax(self.q_proj(x) @ self.k_proj(x).transpose(1, 2) / x.shape[-1] ** 0.5, -1)
        return self.o_proj(att @ self.v_proj(x))


class MLP(nn.Module):
    def __init__(self, d):
        super().__init__()
        self.fc1, self.fc2 = nn.Linear(d, 2 * d), nn.Linear(2 * d, d)

    def forward(self, x):
        return self.fc2(F.gelu(self.fc1(x)))


class Block(nn.Module):
    def __init__(self, d):
        super().__init__()
        self.norm, self.attn, self.mlp = nn.LayerNorm(d), Attention(d), MLP(d)

    def forward(self, x):
        x = x + self.attn(self.norm(x))
        return x + self.mlp(x)


class StandIn(nn.Module):
    """A plain nn.Module with our policy's module names (`backbone.layers.0.attn.q_proj`, ...)."""

    def __init__(self, d=16):
        super().__init__()
        self.embed = nn.Linear(6, d)
        self.backbone = nn.Module()
        self.backbone.layers = nn.ModuleList(Block(d) for _ in range(2))
        self.action_head = nn.Module()
        self.action_head.proj = nn.Linear(d, 4)

    def forward(self, x):
        x = self.embed(x)
        for layer in self.backbone.layers:
            x = layer(x)
        return self.action_head.proj(x)


POLICY = {"d_model": 32, "n_layers": 2, "n_heads": 2, "chunk_size": 4}
KINDS = ["stand_in", "l1_chunk", "flow"]  # the flow policy's expert has the same layer names


def _model(kind: str, seed: int = 0) -> nn.Module:
    torch.manual_seed(seed)
    return StandIn() if kind == "stand_in" else build_policy({"type": kind, **POLICY}, device="cpu")


def _inputs(kind: str):
    g = torch.Generator().manual_seed(1)
    if kind == "stand_in":
        return torch.randn(3, 5, 6, generator=g)
    return {
        "tokens": torch.randint(1, 512, (3, 12), generator=g),
        "state": torch.randn(3, 39, generator=g),
        "proprio": torch.randn(3, 4, generator=g),
    }


def _run(model, inputs) -> torch.Tensor:
    with torch.no_grad():
        if isinstance(inputs, dict):  # a policy: its inference path (flow integrates its velocity)
            return model.sample_actions(inputs)
        return model(inputs)


def _randomize_b(model):
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, LoraLayer):
                for b in m.lora_B.values():
                    b.weight.normal_(std=0.1)


@pytest.mark.parametrize("kind", KINDS)
def test_our_adapter_loads_with_peft_and_merges_to_the_same_checkpoint(tmp_path, kind):
    base = _model(kind)
    ours = copy.deepcopy(base)
    names = apply_lora(ours, LoraConfig(target_modules=TARGETS, r=4, alpha=8))
    assert len(names) == {"flow": 25}.get(kind, 13)  # flow: 2 x 6 expert layers too
    assert "backbone.layers.1.attn.o_proj" in names and "action_head.proj" in names
    _randomize_b(ours)
    out = save_adapter(ours, tmp_path / "adapter")

    theirs = peft.PeftModel.from_pretrained(copy.deepcopy(base), out)
    assert sorted(adapter_modules(theirs.base_model.model)) == sorted(names)
    x = _inputs(kind)
    torch.testing.assert_close(_run(theirs, x), _run(ours, x))

    dense_peft = theirs.merge_and_unload()
    dense_ours = merge_lora(ours)
    mine, peft_state = dense_ours.state_dict(), dense_peft.state_dict()
    assert mine.keys() == peft_state.keys() == base.state_dict().keys()
    assert all(torch.equal(mine[k], peft_state[k]) for k in mine)  # the stored dense checkpoint, exactly
    assert not all(torch.equal(mine[k], v) for k, v in base.state_dict().items())


@pytest.mark.parametrize("kind", KINDS)
def test_peft_made_adapter_loads_with_its_scaling(tmp_path, kind):
    base = _model(kind)
    config = peft.LoraConfig(
        target_modules=["q_proj", "v_proj", "fc1"],
        r=4,
        lora_alpha=8,
        use_rslora=True,
        rank_pattern={"fc1": 2},
        alpha_pattern={"v_proj": 3},
    )
    made = peft.get_peft_model(copy.deepcopy(base), config)
    _randomize_b(made)
    made.save_pretrained(tmp_path / "peft")

    ours = copy.deepcopy(base)
    names = load_adapter(ours, tmp_path / "peft")
    layers = adapter_modules(ours)
    assert len(names) == {"flow": 12}.get(kind, 6)
    assert layers["backbone.layers.0.mlp.fc1"].r["default"] == 2
    assert layers["backbone.layers.0.mlp.fc1"].scaling["default"] == pytest.approx(8 / 2**0.5)
    assert layers["backbone.layers.0.attn.v_proj"].scaling["default"] == pytest.approx(3 / 4**0.5)
    x = _inputs(kind)
    torch.testing.assert_close(_run(ours, x), _run(made, x))
    dense_peft = made.merge_and_unload().state_dict()
    dense_ours = merge_lora(ours).state_dict()
    assert all(torch.equal(dense_ours[k], dense_peft[k]) for k in dense_peft)


def test_policy_config_is_readable_by_peft():
    """peft's merge_and_unload calls model.config.to_dict(); the policy config provides it."""
    policy = _model("l1_chunk")
    assert policy.config.to_dict()["model_type"].startswith("capvector-")


@pytest.mark.parametrize(
    "options",
    [
        {"target_modules": r".*\.(q_proj|fc2)", "exclude_modules": r"backbone\.layers\.1\..*"},
        {
            "target_modules": ["q_proj", "o_proj", "fc1"],
            "layers_to_transform": [1],
            "layers_pattern": "layers",
        },
        {
            "target_modules": ["q_proj", "fc1"],
            "exclude_modules": ["layers.0.attn.q_proj"],
            "rank_pattern": {"fc1": 3, r"layers\.1\.attn\.q_proj": 2},
            "alpha_pattern": {r".*0\.mlp\.fc1": 5},
        },
    ],
)
def test_peft_made_adapter_selects_the_same_modules_as_peft(tmp_path, options):
    """load_adapter matches the file's patterns itself (bounded in time) with peft's rules, then gives peft
    the exact names: the same layers, ranks, scalings and outputs as peft's own loader."""
    base = _model("stand_in")
    made = peft.get_peft_model(copy.deepcopy(base), peft.LoraConfig(r=4, lora_alpha=8, **options))
    _randomize_b(made)
    made.save_pretrained(tmp_path / "peft")
    theirs = peft.PeftModel.from_pretrained(copy.deepcopy(base), tmp_path / "peft")
    ours = copy.deepcopy(base)
    names = load_adapter(ours, tmp_path / "peft")
    want = adapter_modules(theirs.base_model.model)
    assert sorted(names) == sorted(want) and 0 < len(names) < 13
    layers = adapter_modules(ours)
    for n, layer in want.items():
        assert layers[n].r == layer.r and layers[n].scaling == layer.scaling, n
    x = _inputs("stand_in")
    torch.testing.assert_close(_run(ours, x), _run(theirs, x))
