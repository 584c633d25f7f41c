"""LoRA (peft's layers) on a small transformer stand-in: forward, save (peft layout), load, exact merge."""

import json
import re
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file
from torch import nn

from capvector.core.adapters.lora import (
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


# ---------------------------------------------------------------------------- hostile adapter files
def _saved(tmp_path, **config_changes):
    """A real adapter (r=2 on action_head and the linear1 layers) with its config edited."""
    torch.manual_seed(0)
    model = TinyPolicy()
    apply_lora(model, LoraConfig(target_modules=["action_head", "linear1"], r=2))
    _randomize_b(model)
    out = save_adapter(model, tmp_path / "a")
    doc = json.loads((out / "adapter_config.json").read_text())
    (out / "adapter_config.json").write_text(json.dumps({**doc, **config_changes}))  # NaN written as NaN
    return out


def _refuse_building(monkeypatch):
    """From now on, fail the test if peft is asked to build adapter layers (the checks must come first)."""
    import peft

    def refuse(*args, **kwargs):
        raise AssertionError("peft.inject_adapter_in_model was called")

    monkeypatch.setattr(peft, "inject_adapter_in_model", refuse)


def _untouched(model):
    return not adapter_modules(model) and not hasattr(model, "peft_config")


HOSTILE_SCRIPT = """
import json, sys, time
sys.path.insert(0, sys.argv[1])
from torch import nn
from test_lora import TinyPolicy
from capvector.core.adapters.lora import load_adapter
for pattern in json.loads(sys.argv[3]):
    doc = json.loads(open(sys.argv[2] + "/adapter_config.json").read())
    open(sys.argv[2] + "/adapter_config.json", "w").write(json.dumps({**doc, "target_modules": pattern}))
    model = TinyPolicy()
    model.add_module("a" * 40 + "b", nn.Linear(4, 4))  # a long name the pattern almost matches
    start = time.monotonic()
    try:
        load_adapter(model, sys.argv[2])
        message = None
    except ValueError as e:
        message = str(e)
    print(json.dumps({"pattern": pattern, "message": message, "seconds": time.monotonic() - start}))
"""


def test_backtracking_target_patterns_are_refused_in_bounded_time(tmp_path):
    """`re.fullmatch('(a+)+$', 'a' * 40 + 'b')` (what peft runs) backtracks for hours. The file's patterns are
    matched with a time budget; one that needs it all is refused in one line naming it, and peft never runs
    them. Run in a child process: before the fix it never returned (the timeout below fails the test)."""
    import subprocess
    import sys

    out = _saved(tmp_path)
    patterns = [r"(a+)+$", r"(a|aa)+$"]  # the second also backtracks on the `regex` engine: the time budget
    proc = subprocess.run(
        [sys.executable, "-c", HOSTILE_SCRIPT, str(Path(__file__).parent), str(out), json.dumps(patterns)],
        capture_output=True,
        text=True,
        timeout=180,
        cwd=Path(__file__).parents[1],
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    results = [json.loads(line) for line in proc.stdout.splitlines()]
    assert [r["pattern"] for r in results] == patterns
    for r in results:
        assert r["message"] and "\n" not in r["message"] and repr(r["pattern"]) in r["message"], r
    assert "match no module" in results[0]["message"]  # `regex` answers this one at once: no match
    assert "takes over 2 s" in results[1]["message"]


def test_overlong_pattern_refused(tmp_path):
    out = _saved(tmp_path, target_modules="|".join(["action_head"] * 30_000))
    model = TinyPolicy()
    with pytest.raises(ValueError, match=r"target_modules pattern 'action_head\|.*characters long"):
        load_adapter(model, out)
    assert _untouched(model)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"r": 2**16}, r"lora_A.weight is \[2, 32\], the config and layer need \[65536, 32\] \(r=65536\)"),
        ({"rank_pattern": {"action_head": 4}}, r"action_head.lora_A.weight is \[2, 32\].*\[4, 32\] \(r=4\)"),
        ({"lora_alpha": float("nan")}, r"lora_alpha=nan \(a finite number\)"),
        ({"lora_alpha": float("inf")}, r"lora_alpha=inf"),
        ({"alpha_pattern": {"linear1": float("-inf")}}, r"alpha_pattern\['linear1'\]=-inf"),
        ({"lora_dropout": float("nan")}, r"lora_dropout=nan"),
        ({"r": 0}, r"r=0 \(a positive integer\)"),
        ({"r": True}, r"r=True"),
        ({"rank_pattern": {"linear1": 2.5}}, r"rank_pattern\['linear1'\]=2.5"),
        ({"target_modules": "embed|action_head"}, r"unexpected base_model.model.encoder.layers.0.linear1"),
        ({"target_modules": "encoder.layers.0"}, r"only nn.Linear layers .*TransformerEncoderLayer"),
        ({"target_modules": "(unclosed"}, r"target_modules pattern '\(unclosed' is not a valid regex"),
    ],
)
def test_adapter_config_checked_against_its_tensors_before_anything_is_built(
    tmp_path, monkeypatch, changes, message
):
    """A config r = 2**22 against rank-8 tensors used to build 5 GB of layers before the shape check
    failed; NaN alpha loaded. Every check names the field or the tensor, in one line, before peft builds
    a layer."""
    out = _saved(tmp_path, **changes)
    _refuse_building(monkeypatch)
    model = TinyPolicy()
    with pytest.raises(ValueError, match=message) as info:
        load_adapter(model, out)
    assert "\n" not in str(info.value)
    assert _untouched(model) and all(p.requires_grad for p in model.parameters())


def test_non_finite_adapter_tensors_refused(tmp_path, monkeypatch):
    out = _saved(tmp_path)
    _refuse_building(monkeypatch)
    tensors = load_file(out / "adapter_model.safetensors")
    tensors["base_model.model.action_head.lora_B.weight"][0, 0] = float("nan")
    save_file(tensors, out / "adapter_model.safetensors")
    with pytest.raises(ValueError, match=r"action_head.lora_B.weight is not finite"):
        load_adapter(TinyPolicy(), out)
