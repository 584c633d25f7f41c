"""An evaluation runs the policy as trained: a LoRA-SP checkpoint's init + adapter, not its dense merge."""

import pytest
import torch

from capvector.core.adapters import lora_sp
from capvector.core.adapters.lora import LoraConfig
from capvector.core.adapters.lora_sp import LoraSPConfig
from capvector.core.evaluation.rollouts import EvalConfig
from capvector.core.policies.base import Policy, build_policy, load_policy, save_policy
from capvector.core.training.held_out_loss import held_out_action_loss
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.steps import evaluation
from capvector.tasks.steps.held_out_loss import HELD_OUT_LOSS, merge_error
from capvector.tasks.steps.training import run_train
from capvector.tasks.trained_policy import load_trained_policy, policy_form
from tests.test_trainer import TINY, make_dataset, quick

TARGETS = ["mlp.fc*"]


@pytest.fixture(params=["l1_chunk", "flow"])
def trained(tmp_path, request):
    """A workspace with a dataset, an init checkpoint, and one LoRA-SP and one LoRA run from it."""
    workspace = Workspace(str(tmp_path / "home"))
    dataset = make_dataset()
    data_id = workspace.api.register_dir(dataset.save(tmp_path / "data"), kind="dataset", name="demos").id
    torch.manual_seed(0)
    init = build_policy({"type": request.param, **TINY}, "cpu")
    init_id = workspace.api.register_file(
        save_policy(init, tmp_path / "init.safetensors"), kind="checkpoint", name="init"
    ).id
    inputs = {"data": data_id, "init": init_id}
    train = quick(steps=40, lr=1e-2).model_dump(mode="json")
    sp = {"adapter": "lora_sp", "lora_sp": LoraSPConfig(target_modules=TARGETS, bank_size=8).model_dump()}
    lo = {"adapter": "lora", "lora": LoraConfig(target_modules=TARGETS, r=4).model_dump()}
    return workspace, dataset, {
        "lora_sp": run_train(workspace, "sp", inputs, {"train": train, **sp}),
        "lora": run_train(workspace, "lora", inputs, {"train": train, **lo}),
        "init": init_id,
        "data": data_id,
    }


def _actions(policy: Policy, dataset) -> torch.Tensor:
    obs = {key: dataset.tensors[key][:8].numpy() for key in ("state", "proprio")}
    return torch.as_tensor(policy.predict_action_chunk(obs, ["reach-v3"] * 8))


def test_lora_sp_checkpoint_is_evaluated_as_init_plus_adapter(trained):
    workspace, dataset, ids = trained
    policy, form = load_trained_policy(workspace, ids["lora_sp"], device="cpu")
    assert form.form == "lora_sp_adapter" and form.init_id == ids["init"]
    assert not all(m.input_independent for m in lora_sp.sp_modules(policy).values())

    expected = load_policy(workspace.path(ids["init"]), device="cpu")
    lora_sp.load_adapter(expected, workspace.path(form.adapter_id))
    assert torch.equal(_actions(policy, dataset), _actions(expected, dataset))
    merged = load_policy(workspace.path(ids["lora_sp"]), device="cpu")
    assert not torch.allclose(_actions(policy, dataset), _actions(merged, dataset), atol=1e-6)


def test_dense_and_lora_checkpoints_are_evaluated_as_stored(trained):
    workspace, _, ids = trained
    assert policy_form(workspace, ids["lora"]).form == "dense"  # a LoRA merge is exact
    assert policy_form(workspace, ids["init"]).form == "dense"
    policy, _ = load_trained_policy(workspace, ids["lora"], device="cpu")
    assert not lora_sp.sp_modules(policy)


def test_evaluation_record_names_the_form_it_ran(trained, monkeypatch):
    workspace, _, ids = trained
    import prefect.artifacts  # the step imports it when it has run: patched where it is read

    monkeypatch.setattr(prefect.artifacts, "create_table_artifact", lambda **_: None)  # no Prefect API needed
    config = EvalConfig(tasks=["reach-v3"], episodes_per_task=1, horizon=10, execute_steps=4).model_dump()
    record = workspace.api.get(evaluation.evaluate_checkpoint(workspace, "eval", ids["lora_sp"], config))
    assert record.config["policy_form"]["form"] == "lora_sp_adapter"
    assert record.config["policy_form"]["adapter_id"] == policy_form(workspace, ids["lora_sp"]).adapter_id


def test_held_out_loss_is_measured_as_trained_and_names_the_merges_error(trained):
    """A LoRA-SP checkpoint's loss is its adapter's (as evaluated); its dense merge's is recorded beside."""
    workspace, dataset, ids = trained
    inputs = {"checkpoint": ids["lora_sp"], "data": ids["data"]}
    measured = HELD_OUT_LOSS.run(workspace, "loss sp", inputs, {})
    doc = workspace.api.store.open_json(measured)
    policy, _ = load_trained_policy(workspace, ids["lora_sp"], device="cpu")
    assert doc["form"] == "lora_sp_adapter"
    assert doc["action_loss"] == held_out_action_loss(policy, dataset, 256, 0)
    assert doc["merged_action_loss"] == held_out_action_loss(workspace.path(ids["lora_sp"]), dataset, 256, 0)
    assert merge_error(workspace, measured) == doc["merged_action_loss"] - doc["action_loss"] != 0

    dense = HELD_OUT_LOSS.run(workspace, "loss lora", {"checkpoint": ids["lora"], "data": ids["data"]}, {})
    doc = workspace.api.store.open_json(dense)
    assert doc["form"] == "dense" and "merged_action_loss" not in doc
    assert merge_error(workspace, dense) is None
