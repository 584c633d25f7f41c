"""AdaLoRA through peft: ranks pruned by peft's allocator in our loop, peft's orthogonal penalty as an extra
loss, an exact resume, the adapter in peft's layout (loaded by plain peft), the exact dense merge, the
training step and the recipe's arms."""

import copy
import json
from types import SimpleNamespace

import peft
import pytest
import torch
from pydantic import ValidationError
from safetensors.torch import load_file
from torch import nn

from capvector.core.adapters import adalora, lora
from capvector.core.adapters.adalora import AdaLoraConfig, apply_adalora
from capvector.core.policies.base import build_policy, load_policy, save_policy
from capvector.core.training.orthogonal import OrthogonalRegularizer
from capvector.core.training.trainer import train
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.steps.training import TrainStepConfig, run_train
from capvector.tasks.trained_policy import policy_form
from tests.test_trainer import TINY, _as_if_killed_after, make_dataset, quick

TARGETS = ["attn.*_proj", "mlp.fc*"]
SETTINGS = AdaLoraConfig(
    target_modules=TARGETS, init_r=4, target_r=2, tinit_fraction=0.2, tfinal_fraction=0.2
)
STEPS = 20


def _policy(seed: int = 0):
    """θ_pt: its normalizer fitted (kept by training, so θ_pt + the adapter is the trained policy)."""
    torch.manual_seed(seed)
    policy = build_policy({"type": "l1_chunk", **TINY}, "cpu")
    policy.fit_normalizer(make_dataset().tensors)
    return policy


def _train(policy, run_dir, steps: int = STEPS, **kw):
    return train(
        policy,
        make_dataset(),
        quick(steps=steps, lr=1e-2, warmup_steps=2, **kw),
        run_dir,
        extra_losses={"adalora_orth": adalora.orthogonality_loss},
        after_optimizer_step=adalora.schedule(policy),
    )


def _obs(n: int = 6) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(1)
    return {
        "tokens": torch.randint(1, 64, (n, 6), generator=g),
        "state": torch.randn(n, 39, generator=g),
        "proprio": torch.randn(n, 4, generator=g),
    }


def _actions(model, obs) -> torch.Tensor:
    model.eval()
    with torch.no_grad():
        return model.sample_actions(obs)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """θ_pt and an AdaLoRA run from it (20 steps: 4 at init_r, pruning, 4 at the final allocation)."""
    base = _policy()
    model = copy.deepcopy(base)
    names = apply_adalora(model, SETTINGS, STEPS)
    assert adalora.ranks(model) == dict.fromkeys(names, 4)  # nothing pruned yet
    run_dir = tmp_path_factory.mktemp("adalora")
    result = _train(model, run_dir)
    return base, model, names, result


def test_update_and_allocate_prunes_ranks_to_the_budget(trained):
    _, model, names, result = trained
    assert len(names) == 12
    ranks = adalora.ranks(model)
    assert sum(ranks.values()) == SETTINGS.target_r * len(names)  # the final budget, exactly
    assert min(ranks.values()) < SETTINGS.target_r < max(ranks.values())  # unequal: allocated, not cut
    for name, keep in adalora.kept_triplets(model).items():  # pruned triplets carry no update
        e = adalora.adalora_modules(model)[name].lora_E["default"].detach().flatten()
        assert bool((e[~keep] == 0).all()) and bool((e[keep] != 0).all()), name
    rows = [json.loads(line) for line in result.loss_curve_path.read_text().splitlines()]
    assert all(r["adalora_orth"] > 0 for r in rows)  # peft's orthogonal penalty trained alongside


class _WithLoss(nn.Module):
    """A model whose output has `.loss` (0): peft's AdaLoraModel.forward adds its penalty to it."""

    def __init__(self):
        super().__init__()
        self.fc1, self.fc2 = nn.Linear(6, 8), nn.Linear(8, 5)

    def forward(self, x):
        self.fc2(self.fc1(x))
        return SimpleNamespace(loss=torch.zeros(()))


def test_orthogonality_loss_is_peft_s_value_and_trains_a_and_b():
    torch.manual_seed(0)
    model = _WithLoss()
    apply_adalora(model, AdaLoraConfig(target_modules=["fc*"], init_r=3, target_r=2, orth_reg_weight=0.3), 10)
    with torch.no_grad():
        for m in adalora.adalora_modules(model).values():
            m.lora_A["default"].normal_()
            m.lora_B["default"].normal_()
    ours = adalora.orthogonality_loss(model)
    theirs = adalora.schedule(model).tuner(torch.randn(2, 6)).loss
    assert float(ours.detach()) > 0 and torch.equal(ours, theirs)
    ours.backward()
    layer = model.fc1
    assert layer.lora_A["default"].grad is not None and layer.lora_B["default"].grad is not None
    with pytest.raises(ValueError, match="no AdaLoRA rank schedule"):
        adalora.orthogonality_loss(nn.Linear(2, 2))


# peft's own AdaLoRA files warn too: its loader reads rank_pattern's `<module>.lora_E` keys as LoRA's
@pytest.mark.filterwarnings("ignore:The following rank_pattern keys did not match")
def test_saved_adapter_loads_in_plain_peft_with_the_same_outputs(trained, tmp_path):
    base, model, names, _ = trained
    out = adalora.save_adapter(model, tmp_path / "adapter")
    doc = json.loads((out / "adapter_config.json").read_text())
    assert doc["peft_type"] == "ADALORA" and doc["total_step"] == STEPS
    assert (doc["tinit"], doc["tfinal"], doc["init_r"], doc["target_r"]) == (4, 4, 4, 2)
    ranks = adalora.ranks(model)
    assert {k.removesuffix(".lora_E"): sum(v) for k, v in doc["rank_pattern"].items()} == ranks
    tensors = load_file(out / "adapter_model.safetensors")
    assert len(tensors) == 3 * len(names)
    name = min(ranks, key=ranks.get)  # cut to its kept triplets (possibly none)
    assert tensors[f"base_model.model.{name}.lora_A"].shape == (ranks[name], 32)
    assert tensors[f"base_model.model.{name}.lora_B"].shape == (32 if "attn" in name else 128, ranks[name])

    theirs = peft.PeftModel.from_pretrained(copy.deepcopy(base), out)
    loaded = adalora.adalora_modules(theirs.base_model.model)
    assert {n: m.r["default"] for n, m in loaded.items()} == ranks
    obs = _obs()
    torch.testing.assert_close(_actions(theirs, obs), _actions(model, obs))
    with pytest.raises(TypeError, match="adalora.save_adapter"):
        lora.save_adapter(model, tmp_path / "as_lora")


def test_merged_dense_model_matches_the_adapter_model(trained):
    base, model, _, _ = trained
    merged = adalora.merge_adalora(copy.deepcopy(model))
    assert not lora.adapter_modules(merged) and not hasattr(merged, adalora.SCHEDULE_ATTRIBUTE)
    assert merged.state_dict().keys() == base.state_dict().keys()
    obs = _obs()
    torch.testing.assert_close(_actions(merged, obs), _actions(model, obs))
    changed = [k for k, v in base.state_dict().items() if not torch.equal(v, merged.state_dict()[k])]
    assert changed and all(".attn." in k or ".mlp." in k for k in changed)


def test_resume_is_exact_with_the_allocator_state_in_the_checkpoint(tmp_path):
    """A run stopped after step 8 (pruning under way) and resumed allocates as an uninterrupted one: the
    allocator's EMAs and rank pattern are in the checkpoint (without them the masks would differ)."""

    def fresh():
        model = _policy()
        apply_adalora(model, SETTINGS, STEPS)
        return model

    kw = dict(checkpoint_every=4, keep_checkpoints=10)
    straight = fresh()
    _train(straight, tmp_path / "straight", **kw)
    _train(fresh(), tmp_path / "run", **kw)
    _as_if_killed_after(tmp_path / "run", 8)
    state = torch.load(tmp_path / "run/checkpoints/step_00000008/trainer_state.pt", weights_only=True)
    assert state["step_hook"]["rank_pattern"] and state["step_hook"]["exp_avg_ipt"]
    resumed = fresh()
    assert _train(resumed, tmp_path / "run", **kw).resumed_from_step == 8
    assert adalora.ranks(resumed) == adalora.ranks(straight)
    a, b = resumed.state_dict(), straight.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.filterwarnings("ignore:The following rank_pattern keys did not match")
def test_training_step_registers_a_peft_adapter_and_a_dense_checkpoint(tmp_path):
    workspace = Workspace(str(tmp_path / "home"))
    data_id = workspace.api.register_dir(make_dataset().save(tmp_path / "data"), kind="dataset", name="d").id
    base = _policy()
    init_id = workspace.api.register_file(
        save_policy(base, tmp_path / "init.safetensors"), kind="checkpoint", name="init"
    ).id
    config = {
        "train": quick(steps=STEPS, lr=1e-2, warmup_steps=2).model_dump(mode="json"),
        "adapter": "adalora",
        "adalora": SETTINGS.model_dump(),
    }
    checkpoint_id = run_train(workspace, "ada", {"data": data_id, "init": init_id}, config)
    record = workspace.api.get(checkpoint_id)
    ranks = record.config["summary"]["active_ranks"]
    assert sum(ranks.values()) == SETTINGS.target_r * 12
    adapter_id = {p.role: p.id for p in record.parents}["adapter"]
    assert policy_form(workspace, checkpoint_id).form == "dense"  # the merge is exact: evaluated as stored
    dense = load_policy(workspace.path(checkpoint_id), device="cpu")
    init = load_policy(workspace.path(init_id), device="cpu")
    theirs = peft.PeftModel.from_pretrained(init, workspace.path(adapter_id))
    obs = _obs()
    torch.testing.assert_close(_actions(dense, obs), _actions(theirs, obs))


def test_config_refuses_a_schedule_without_pruning_steps_and_too_large_a_target():
    halves = SETTINGS.model_copy(update={"tinit_fraction": 0.5, "tfinal_fraction": 0.5}).model_dump()
    with pytest.raises(ValidationError, match=r"10 steps has no step to prune ranks in: tinit_fraction 0.5"):
        TrainStepConfig(train=quick(steps=10, warmup_steps=1), adapter="adalora", adalora=halves)
    TrainStepConfig(train=quick(steps=10, warmup_steps=1), adapter="adalora", adalora=SETTINGS.model_dump())
    assert SETTINGS.schedule(2) == (0, 1)  # at least 1 final step, which forces the final allocation
    with pytest.raises(ValidationError, match="target_r"):
        AdaLoraConfig(target_modules=TARGETS, init_r=4, target_r=5)
    with pytest.raises(ValidationError, match="needs a `adalora` config"):
        TrainStepConfig(train=quick(), adapter="adalora")


def test_recipe_arms_and_the_orthogonal_loss_on_adalora_layers():
    """`capvector_adalora` penalises ΔW = B·diag(E)·A·alpha/(init_r + 1e-5) against γ (lora_exact)."""
    from capvector.flows.recipe.config import load_config

    config = load_config("smoke", ["adapter_lr=3e-3"])
    sft, cap = config.downstream_step("sft_adalora", 0), config.downstream_step("capvector_adalora", 0)
    assert sft.adapter == cap.adapter == "adalora" and sft.adalora == config.adalora and sft.lora is None
    assert sft.orthogonal is None and cap.orthogonal is not None and cap.train.lr == 3e-3

    torch.manual_seed(0)
    model = nn.Sequential(nn.Linear(5, 6), nn.ReLU(), nn.Linear(6, 3))
    gamma = {k: torch.randn_like(v) for k, v in model.state_dict().items()}
    apply_adalora(model, AdaLoraConfig(target_modules=["0", "2"], init_r=3, target_r=2, alpha=6), 10)
    layers = adalora.adalora_modules(model)
    with torch.no_grad():
        for m in layers.values():
            m.lora_E["default"].normal_()
    exact = OrthogonalRegularizer(model, gamma, mode="lora_exact", lambda_absolute=0.5)
    a_only = OrthogonalRegularizer(model, gamma, mode="lora_a", lambda_absolute=0.5)

    def delta(m):
        return m.lora_B["default"] @ (m.lora_A["default"] * m.lora_E["default"]) * 6 / (3 + 1e-5)

    want = sum((gamma[f"{n}.weight"] * delta(m)).abs().sum() for n, m in layers.items())
    loss = exact(model)
    torch.testing.assert_close(loss, 0.5 * want.detach())
    loss.backward()
    assert all(m.lora_E["default"].grad is not None for m in layers.values())
    want_a = sum((gamma[f"{n}.weight"] @ m.lora_A["default"].T).abs().sum() for n, m in layers.items())
    torch.testing.assert_close(a_only(model), 0.5 * want_a.detach())
