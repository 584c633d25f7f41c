"""Expert demonstration collection and the DemoDataset file format."""

import json

import pytest
import torch
from pydantic import ValidationError
from safetensors.torch import load_file, save_file

from capvector.core.simulation.demos import (
    DATA_FILE,
    META_FILE,
    SUCCESS_TAIL,
    TRAIN_SEED_BASE,
    DemoConfig,
    DemoDataset,
    collect_demos,
)


@pytest.fixture(scope="module")
def state_demos():
    calls = []
    config = DemoConfig(tasks=["reach-v3", "drawer-close-v3"], episodes_per_task=3, horizon=150, workers=2)
    dataset = collect_demos(config, progress=lambda done, total: calls.append((done, total)))
    return dataset, calls


def test_collection_keeps_successful_episodes_with_contract_fields(state_demos):
    dataset, calls = state_demos
    meta, t = dataset.meta, dataset.tensors
    assert meta.n_episodes == 6 and meta.failures == {"reach-v3": 0, "drawer-close-v3": 0}
    assert all(len(s) == 3 and min(s) >= TRAIN_SEED_BASE for s in meta.seeds.values())
    n = len(dataset)
    expected = {"state": (39,), "proprio": (4,), "privileged": (9,), "action": (4,)}
    for key, shape in expected.items():
        assert t[key].shape == (n, *shape) and t[key].dtype == torch.float32
    for key in ("episode", "step", "task"):
        assert t[key].shape == (n,) and t[key].dtype == torch.int64
    assert "image" not in t
    assert t["episode"].unique().tolist() == list(range(6))
    assert t["task"][t["episode"] == 0].unique().tolist() == [0]
    assert t["task"][t["episode"] == 5].unique().tolist() == [1]
    assert (t["step"][t["episode"] == 0] == torch.arange(int((t["episode"] == 0).sum()))).all()
    assert calls[-1] == (6, 6) and [c[0] for c in calls] == sorted(c[0] for c in calls)
    assert meta.instructions[0] == "reach the goal position with the gripper"


def test_episodes_stop_shortly_after_success(state_demos):
    dataset, _ = state_demos
    lengths = torch.bincount(dataset.tensors["episode"])
    assert lengths.max() < 150 and lengths.min() > SUCCESS_TAIL


def test_collection_does_not_depend_on_worker_count(state_demos):
    dataset, _ = state_demos
    single = collect_demos(DemoConfig(tasks=["reach-v3"], episodes_per_task=3, horizon=150, workers=1))
    first = dataset.tensors["task"] == 0
    torch.testing.assert_close(single.tensors["state"], dataset.tensors["state"][first], rtol=0, atol=0)


def test_normalization_stats(state_demos):
    dataset, _ = state_demos
    stats = dataset.normalization_stats()
    assert set(stats) == {"state", "proprio", "privileged", "action"}
    torch.testing.assert_close(stats["action"]["mean"], dataset.tensors["action"].mean(0))
    assert (stats["state"]["std"] >= 1e-2).all()  # zero-padding dims are floored, not zero


def test_save_load_roundtrip_is_exact(state_demos, tmp_path):
    dataset, _ = state_demos
    dataset.save(tmp_path / "ds")
    loaded = DemoDataset.load(tmp_path / "ds")
    assert loaded.meta == dataset.meta and loaded.content_hash == dataset.content_hash
    assert set(loaded.tensors) == set(dataset.tensors)
    for key in dataset.tensors:
        assert torch.equal(loaded.tensors[key], dataset.tensors[key])
    assert not list(tmp_path.glob(".ds.tmp-*"))
    with pytest.raises(FileExistsError):
        dataset.save(tmp_path / "ds")
    dataset.save(tmp_path / "ds", overwrite=True)
    assert DemoDataset.load(tmp_path / "ds").content_hash == dataset.content_hash


def test_hash_is_stable_and_follows_the_data(state_demos):
    dataset, _ = state_demos
    assert dataset.compute_hash() == dataset.content_hash
    changed = {k: v.clone() for k, v in dataset.tensors.items()}
    changed["action"][0, 0] += 1e-3
    assert DemoDataset(changed, dataset.meta).compute_hash() != dataset.content_hash
    renamed = dataset.meta.model_copy(update={"camera": "corner3"})
    assert DemoDataset(dataset.tensors, renamed).compute_hash() != dataset.content_hash


def test_tampered_or_incomplete_datasets_fail_clearly(state_demos, tmp_path):
    dataset, _ = state_demos
    path = dataset.save(tmp_path / "ds")
    tensors = load_file(str(path / DATA_FILE))
    tensors["action"][0, 0] += 1.0
    save_file(tensors, str(path / DATA_FILE))
    with pytest.raises(ValueError, match="content hash mismatch"):
        DemoDataset.load(path)
    del tensors["step"]
    save_file(tensors, str(path / DATA_FILE))
    with pytest.raises(ValueError, match=r"lacks required field\(s\) \['step'\]"):
        DemoDataset.load(path)
    meta = json.loads((path / META_FILE).read_text())
    del meta["tasks"]
    (path / META_FILE).write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="not valid dataset metadata"):
        DemoDataset.load(path)
    (path / META_FILE).unlink()
    with pytest.raises(FileNotFoundError, match="meta.json is missing"):
        DemoDataset.load(path)


def test_require_fields_names_what_is_missing(state_demos):
    dataset, _ = state_demos
    dataset.require_fields(["privileged", "action"], "spatial")
    without = {k: v for k, v in dataset.tensors.items() if k != "privileged"}
    with pytest.raises(ValueError, match=r"spatial needs dataset field\(s\) \['privileged'\]"):
        DemoDataset(without, dataset.meta).require_fields(["privileged"], "spatial")


def test_pixel_demos_store_uint8_images():
    config = DemoConfig(tasks=["reach-v3"], episodes_per_task=1, obs_mode="pixels", image_size=32, workers=1)
    dataset = collect_demos(config)
    image = dataset.tensors["image"]
    assert image.dtype == torch.uint8 and image.shape == (len(dataset), 32, 32, 3)
    assert "image" not in dataset.normalization_stats()


def test_bad_demo_configs_are_rejected():
    with pytest.raises(ValidationError, match="unknown Meta-World v3 task"):
        DemoConfig(tasks=["reach-v2"])
    with pytest.raises(ValidationError, match="beyond the training range"):
        DemoConfig(tasks=["reach-v3"], episodes_per_task=10, seed_offset=9990)
    with pytest.raises(ValidationError, match="unknown camera"):
        DemoConfig(tasks=["reach-v3"], camera="top")
