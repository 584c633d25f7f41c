"""A training step killed on one machine resumes on another (issue 23, item 5).

Each resumable checkpoint is copied to a shared scratch folder (capvector.tasks.runtime.scratch:
`<home>/scratch` for a home on S3, here a local moto server; `CAPVECTOR_SCRATCH` for any home), files first
and the manifest naming them last. The same step run on another machine (another CAPVECTOR_CACHE: no local run
dir) fetches the newest complete one and the trainer resumes from it: the same weights, bit for bit, as an
uninterrupted run. The scratch folder is removed once the step's checkpoint is registered.
"""

import json
import shutil
import uuid
from pathlib import Path

import pytest
from safetensors.torch import load_file

from capvector.artifacts import catalogue as catalogue_mod
from capvector.tasks.runtime.caching import content_key
from capvector.tasks.runtime.scratch import MANIFEST, SCRATCH_ENV, CheckpointMirror
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.steps import training
from capvector.tasks.steps.training import TrainStepConfig, run_train
from tests.test_trainer import TINY, make_dataset, quick

TRAIN = dict(
    steps=12, warmup_steps=2, checkpoint_every=4, log_every=4, keep_checkpoints=1, snapshot_steps=[2, 6]
)  # a resume averages its first curve row from the resume step: rows at checkpoints compare
CONFIG = {"policy": {"type": "l1_chunk", **TINY}, "train": quick(**TRAIN).model_dump(mode="json")}


class Preempted(BaseException):
    """The node going away (like KeyboardInterrupt, nothing on the way catches it)."""


@pytest.fixture
def bucket(s3_endpoint, monkeypatch):
    boto3 = pytest.importorskip("boto3")
    monkeypatch.setattr(catalogue_mod, "SETTLE_NS", 0)
    monkeypatch.delenv(SCRATCH_ENV, raising=False)
    name = f"capvector-{uuid.uuid4().hex[:12]}"
    client = boto3.client("s3")
    client.create_bucket(Bucket=name)
    return name, client


def keys_under(client, bucket: str, prefix: str) -> list[str]:
    pages = client.get_paginator("list_objects_v2").paginate(Bucket=bucket, Prefix=prefix)
    return sorted(o["Key"][len(prefix) :] for page in pages for o in page.get("Contents", []))


def kill_at(monkeypatch, step: int) -> None:
    """The next training run dies right after its checkpoint at `step` is saved (and copied)."""
    real = training.train

    def train(*args, on_checkpoint=None, **kwargs):
        def hook(at, folder):
            if on_checkpoint is not None:
                on_checkpoint(at, folder)
            if at == step:
                raise Preempted(f"killed after the checkpoint at step {at}")

        return real(*args, on_checkpoint=hook, **kwargs)

    monkeypatch.setattr(training, "train", train)


def machine(monkeypatch, cache: Path, home: str) -> Workspace:
    monkeypatch.setenv("CAPVECTOR_CACHE", str(cache))
    return Workspace(home)


def curve_without_times(record) -> list[dict]:
    return [{k: v for k, v in row.items() if k != "time"} for row in record.config["curve"]]


def test_a_step_killed_on_one_machine_resumes_on_another_bit_for_bit(bucket, tmp_path, monkeypatch):
    name, client = bucket
    home = f"s3://{name}/home"

    # machine A: trains, copies its checkpoints at steps 4 and 8 to <home>/scratch, dies after 8
    a = machine(monkeypatch, tmp_path / "machine-a", home)
    data = a.api.register_dir(make_dataset().save(tmp_path / "data"), kind="dataset", name="d").id
    inputs = {"data": data}
    config = TrainStepConfig.model_validate(CONFIG)
    key = content_key("train", inputs, config, "capvector.tasks.steps.training")
    with monkeypatch.context() as m:
        kill_at(m, 8)
        with pytest.raises(Preempted):
            run_train(a, "sft", inputs, CONFIG)
    assert [p.name for p in (a.run_dir(key) / "checkpoints").iterdir()] == ["step_00000008"]
    scratch = keys_under(client, name, f"home/scratch/{key}/")
    assert scratch == [
        MANIFEST,
        "snapshots/step_00000002.safetensors",
        "snapshots/step_00000006.safetensors",
        "step_00000008/loss_curve.jsonl",
        "step_00000008/policy.safetensors",
        "step_00000008/train_config.json",
        "step_00000008/trainer_state.pt",
    ]  # the checkpoint at 4 was removed once 8 was whole; nothing went into the content-addressed store
    manifest = json.loads(client.get_object(Bucket=name, Key=f"home/scratch/{key}/{MANIFEST}")["Body"].read())
    assert manifest["step"] == 8 and sorted(manifest["files"]) == [k for k in scratch if k != MANIFEST]
    assert not any(key in k for k in keys_under(client, name, "home/store/"))

    # machine B: no run dir of its own; resumes from step 8 and finishes
    b = machine(monkeypatch, tmp_path / "machine-b", home)
    assert not (b.work_dir / key[:32]).exists()
    resumed = run_train(b, "sft", inputs, CONFIG)
    record = b.api.get(resumed)
    assert record.config["summary"]["resumed_from_step"] == 8
    assert keys_under(client, name, "home/scratch/") == []  # removed once the checkpoint is registered
    assert not (b.work_dir / key[:32]).exists()

    # an uninterrupted run (a local home, no scratch): the same checkpoint, snapshots and curve
    monkeypatch.delenv("CAPVECTOR_CACHE")
    reference = Workspace(str(tmp_path / "reference"))
    dataset = make_dataset().save(tmp_path / "data2")
    assert reference.api.register_dir(dataset, kind="dataset", name="d").id == data
    uninterrupted = run_train(reference, "sft", inputs, CONFIG)
    ref_record = reference.api.get(uninterrupted)
    assert ref_record.config["summary"]["resumed_from_step"] == 0
    ours, theirs = load_file(str(b.path(resumed))), load_file(str(reference.path(uninterrupted)))
    assert ours.keys() == theirs.keys()
    assert all(ours[k].equal(theirs[k]) for k in ours)
    assert resumed == uninterrupted  # the same bytes, the same id
    assert record.config["snapshots"] == ref_record.config["snapshots"]
    assert curve_without_times(record) == curve_without_times(ref_record)


def test_a_local_home_copies_checkpoints_only_to_a_configured_scratch_url(tmp_path, monkeypatch):
    """CAPVECTOR_SCRATCH for a local home (here a path standing for a shared one): a rerun whose run
    dir is gone resumes from the copy; without it a local home copies nothing."""
    monkeypatch.delenv(SCRATCH_ENV, raising=False)
    workspace = Workspace(str(tmp_path / "home"))
    assert workspace.checkpoint_mirror("k" * 64) is None

    shared = tmp_path / "shared-scratch"
    monkeypatch.setenv(SCRATCH_ENV, f"file://{shared}")
    data = workspace.api.register_dir(make_dataset().save(tmp_path / "data"), kind="dataset", name="d").id
    inputs = {"data": data}
    config = TrainStepConfig.model_validate(CONFIG)
    key = content_key("train", inputs, config, "capvector.tasks.steps.training")
    with monkeypatch.context() as m:
        kill_at(m, 4)
        with pytest.raises(Preempted):
            run_train(workspace, "sft", inputs, CONFIG)
    assert json.loads((shared / key / MANIFEST).read_text())["step"] == 4
    shutil.rmtree(workspace.run_dir(key))  # as if on a machine that never ran it
    resumed = run_train(workspace, "sft", inputs, CONFIG)
    assert workspace.api.get(resumed).config["summary"]["resumed_from_step"] == 4
    assert not (shared / key).exists()


def fake_run(run_dir: Path, step: int, snapshots=()) -> Path:
    """A run dir holding a checkpoint at `step` (files with recognisable bytes) and its curve."""
    folder = run_dir / "checkpoints" / f"step_{step:08d}"
    folder.mkdir(parents=True)
    for f in ("policy.safetensors", "trainer_state.pt", "train_config.json"):
        (folder / f).write_bytes(f"{f} at {step}".encode())
    rows = [json.dumps({"step": s}) + "\n" for s in range(1, step + 1)]
    (run_dir / "loss_curve.jsonl").write_text("".join(rows))
    for s in snapshots:
        (run_dir / "snapshots").mkdir(exist_ok=True)
        (run_dir / "snapshots" / f"step_{s:08d}.safetensors").write_bytes(f"snapshot {s}".encode())
    return folder


def test_only_a_whole_copy_is_fetched_and_never_over_a_newer_local_checkpoint(tmp_path, capfd):
    scratch = tmp_path / "scratch"
    mirror = CheckpointMirror(str(scratch), "k" * 64)
    src = tmp_path / "a"
    mirror.save(3, fake_run(src, 3, snapshots=[2]), src)
    copy = scratch / ("k" * 64)

    # files of a newer checkpoint without the manifest naming them: a half-written copy, not used
    (copy / "step_00000005").mkdir()
    (copy / "step_00000005" / "policy.safetensors").write_bytes(b"half")
    there = tmp_path / "b"
    assert mirror.restore(there) == 3
    assert sorted(p.name for p in (there / "checkpoints").iterdir()) == ["step_00000003"]
    fetched = there / "checkpoints" / "step_00000003"
    assert (fetched / "trainer_state.pt").read_bytes() == b"trainer_state.pt at 3"
    assert (there / "snapshots" / "step_00000002.safetensors").read_bytes() == b"snapshot 2"
    assert (there / "loss_curve.jsonl").read_text() == (src / "loss_curve.jsonl").read_text()

    # a newer checkpoint here is kept; an older one is joined by the copy's
    assert mirror.restore(there) == 0
    older = tmp_path / "c"
    fake_run(older, 1)
    assert mirror.restore(older) == 3
    assert sorted(p.name for p in (older / "checkpoints").iterdir()) == ["step_00000001", "step_00000003"]

    # the next copy replaces the previous one (and the half-written leftover) once it is whole
    mirror.save(6, fake_run(src, 6, snapshots=[2]), src)
    assert sorted(p.name for p in copy.iterdir()) == [MANIFEST, "snapshots", "step_00000006"]

    # a file cut short after the manifest was written: nothing is fetched, one warning line
    (copy / "step_00000006" / "trainer_state.pt").write_bytes(b"cut")
    fresh = tmp_path / "d"
    fresh.mkdir()
    assert mirror.restore(fresh) == 0
    assert "checkpoint at step 6 not fetched" in capfd.readouterr().err
    assert not (fresh / "checkpoints").exists() or not any((fresh / "checkpoints").iterdir())
    assert not (fresh / "loss_curve.jsonl").exists()

    mirror.clear()
    assert not copy.exists()
