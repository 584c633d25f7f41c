"""An adapter run keeps its policy at every snapshot budget (the rank study tests LoRA, LoRA-SP and AdaLoRA
at each budget like full fine-tuning): each snapshot is the run's merge at that step, writing it leaves the
training itself untouched, and a LoRA-SP snapshot is evaluated as `init` + its own adapter."""

import pytest
import torch

from capvector.core.adapters.adalora import AdaLoraConfig
from capvector.core.adapters.lora import LoraConfig
from capvector.core.adapters.lora_sp import LoraSPConfig
from capvector.core.policies.base import build_policy, load_policy, save_policy
from capvector.core.vectors.safetensors_io import Checkpoint
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.steps.training import run_train, snapshots_of
from capvector.tasks.trained_policy import load_trained_policy, policy_form
from tests.test_trainer import TINY, make_dataset, quick

TARGETS = ["mlp.fc*"]
FORMS = {
    "lora": {"lora": LoraConfig(target_modules=TARGETS, r=4)},
    "lora_sp": {"lora_sp": LoraSPConfig(target_modules=TARGETS, bank_size=8)},
    "adalora": {"adalora": AdaLoraConfig(target_modules=TARGETS, init_r=4, target_r=2)},
}


@pytest.fixture
def stage(tmp_path):
    workspace = Workspace(str(tmp_path / "home"))
    data_id = workspace.api.register_dir(make_dataset().save(tmp_path / "data"), kind="dataset", name="d").id
    torch.manual_seed(0)
    init = build_policy({"type": "l1_chunk", **TINY}, "cpu")
    init_id = workspace.api.register_file(
        save_policy(init, tmp_path / "init.safetensors"), kind="checkpoint", name="init"
    ).id
    return workspace, {"data": data_id, "init": init_id}


def _tensors(path) -> dict[str, torch.Tensor]:
    ckpt = Checkpoint(path)
    return {k: ckpt.get(k) for k in ckpt.keys()}


@pytest.mark.parametrize("form", list(FORMS))
def test_an_adapter_run_keeps_its_merge_at_each_budget_without_changing_its_training(stage, form):
    workspace, inputs = stage
    sections = {k: v.model_dump() for k, v in FORMS[form].items()}
    plain = quick(steps=12, lr=1e-2).model_dump(mode="json")
    kept = {**plain, "snapshot_steps": [4, 8]}
    step = {"adapter": form, **sections}
    with_snapshots = run_train(workspace, f"{form} kept", inputs, {"train": kept, **step})
    without = run_train(workspace, f"{form} plain", inputs, {"train": plain, **step})
    final, other = _tensors(workspace.path(with_snapshots)), _tensors(workspace.path(without))
    assert final.keys() == other.keys()
    for name in final:  # writing snapshots drew nothing from the run's random streams
        assert torch.equal(final[name], other[name]), name
    budgets = snapshots_of(workspace, with_snapshots)
    assert sorted(budgets) == [4, 8, 12]
    early = _tensors(workspace.path(budgets[4]))
    assert early.keys() == final.keys()  # dense, merged: the policy's own tensor names
    assert any(not torch.equal(early[n], final[n]) for n in final)
    load_policy(workspace.path(budgets[4]), device="cpu")
    shape = policy_form(workspace, budgets[4])
    if form == "lora_sp":
        assert shape.form == "lora_sp_adapter" and shape.init_id == inputs["init"]
        assert shape.adapter_id != policy_form(workspace, with_snapshots).adapter_id  # its own adapter
        load_trained_policy(workspace, budgets[4], device="cpu")
    else:
        assert shape.form == "dense"
