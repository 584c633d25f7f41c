"""Where a step runs is not part of its cache key, and is in its record (issue 23, item 4).

The fields that only say where or how fast a step runs are marked `ExecutionOnly` on their models
(capvector.core.training.execution) and left out of the content key: the same training run asked for on
`cuda:0` or with 8 threads is a hit for one trained on a CPU with 1. The checkpoint's record says what
the run actually used (`config.execution`: the resolved device, never `auto`, and the thread count).
"""

import json

import torch
from typer.testing import CliRunner

from capvector.core.evaluation.rollouts import EvalConfig
from capvector.core.simulation.demos import DemoConfig
from capvector.core.training.device import device_label, resolve_device
from capvector.core.training.execution import execution_only_fields, result_config
from capvector.core.training.trainer import TrainConfig
from capvector.flows.cli.main import app
from capvector.tasks.runtime.caching import content_key, step_outcomes
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.steps.training import TrainStepConfig, run_train
from tests.test_trainer import TINY, make_dataset, quick

INPUTS = {"data": "a" * 64}


def train_key(**train) -> str:
    step = TrainStepConfig(policy={"type": "l1_chunk", **TINY}, train=quick(**train))
    return content_key("train", INPUTS, step, "capvector.tasks.steps.training")


def test_the_execution_only_fields_are_these():
    """The docstring of capvector.core.training.execution lists these, with why each cannot change a
    result."""
    assert set(execution_only_fields(TrainConfig)) == {
        "device",
        "num_threads",
        "checkpoint_every",
        "keep_checkpoints",
    }
    assert set(execution_only_fields(DemoConfig)) == {"workers"}
    assert set(execution_only_fields(EvalConfig)) == {"batch_size"}


def test_device_and_thread_count_leave_the_key_a_learning_rate_does_not():
    base = train_key(device="cpu", num_threads=1)
    for placement in (
        {"device": "cuda:0", "num_threads": 1},
        {"device": "auto", "num_threads": None},
        {"device": "cpu", "num_threads": 8},
        {"device": "cuda", "num_threads": 4, "checkpoint_every": 3, "keep_checkpoints": 5},
    ):
        assert train_key(**placement) == base, placement
    assert train_key(device="cpu", num_threads=1, lr=1e-3) != base
    assert train_key(device="cuda:0", num_threads=8, lr=1e-3) == train_key(device="cpu", lr=1e-3)
    assert train_key(device="cpu", num_threads=1, log_every=3) != base  # the recorded curve changes
    assert train_key(device="cpu", num_threads=1, seed=1) != base

    # the fields are gone at any depth of the dump, and only they are
    dumped = result_config(TrainStepConfig(policy={"type": "l1_chunk", **TINY}, train=quick()))
    assert {"device", "num_threads", "checkpoint_every", "keep_checkpoints"}.isdisjoint(dumped["train"])
    assert dumped["train"]["lr"] == quick().lr and dumped["policy"]["d_model"] == TINY["d_model"]


def test_demo_workers_and_evaluation_batch_size_leave_the_key():
    def demo_key(**kw):
        config = DemoConfig(tasks=["reach-v3"], episodes_per_task=3, **kw)
        return content_key("collect_demos", {}, config, "capvector.tasks.steps.data")

    assert demo_key(workers=1) == demo_key(workers=4)
    assert demo_key(workers=1) != demo_key(workers=1, horizon=100)

    def eval_key(**kw):
        config = EvalConfig(tasks=["reach-v3"], episodes_per_task=3, **kw)
        return content_key("evaluate", {"checkpoint": "c" * 64}, config, "capvector.tasks.steps.evaluation")

    assert eval_key(batch_size=1) == eval_key(batch_size=64)
    assert eval_key(batch_size=1) != eval_key(batch_size=1, record_video=1)  # it registers videos
    assert eval_key(record_video=1) != eval_key(record_video=1, video_size=224)  # other videos


def test_a_trained_checkpoint_records_where_it_ran_and_another_placement_is_a_hit(tmp_path):
    workspace = Workspace(str(tmp_path / "home"))
    data = workspace.api.register_dir(make_dataset().save(tmp_path / "data"), kind="dataset", name="d").id
    train = dict(steps=6, warmup_steps=1, checkpoint_every=3, snapshot_steps=[3])

    def config(**placement):
        return {"policy": {"type": "l1_chunk", **TINY}, "train": quick(**{**train, **placement}).model_dump()}

    threads = torch.get_num_threads()
    try:
        with step_outcomes() as outcomes:
            first = run_train(workspace, "sft", {"data": data}, config(device="auto", num_threads=1))
            again = run_train(
                workspace, "sft", {"data": data}, config(device="cpu", num_threads=2, checkpoint_every=2)
            )
    finally:
        torch.set_num_threads(threads)
    assert again == first and outcomes == ["produced", "cached"]

    record = workspace.api.get(first)
    execution = record.config["execution"]
    assert execution["device"] == device_label(resolve_device("auto"))  # resolved: never "auto"
    assert execution["num_threads"] == 1
    assert execution["torch"] == torch.__version__
    assert execution["cuda_available"] is torch.cuda.is_available()
    assert record.config["train_step"]["train"]["device"] == "auto"  # what was asked stays recorded
    (snapshot,) = [p.id for p in record.parents if p.role == "snapshot"]
    assert workspace.api.get(snapshot).config["execution"] == execution

    shown = CliRunner().invoke(app, ["--home", workspace.home, "artifacts", "show", first[:12]])
    assert shown.exit_code == 0, shown.output
    assert json.loads(shown.output)["config"]["execution"]["device"] == execution["device"]
