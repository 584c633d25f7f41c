"""The streaming reader/writer: round trips, sharding, atomicity, header validation."""

import json

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file

from capvector_core.safetensors_io import (
    INDEX_NAME,
    Checkpoint,
    CheckpointError,
    ShardedWriter,
    file_sha256,
    write_checkpoint,
)


def _tensors():
    g = torch.Generator().manual_seed(0)
    return {
        "a.weight": torch.randn(64, 64, generator=g),
        "a.bias": torch.randn(64, generator=g).to(torch.bfloat16),
        "b.mask": torch.rand(7, generator=g) > 0.5,
        "b.step": torch.tensor(3),
        "c.weight": torch.randn(3, 5, generator=g).half(),
    }


def test_single_file_round_trip_is_standard_safetensors(tmp_path):
    t = _tensors()
    out = tmp_path / "x.safetensors"
    write_checkpoint(out, t, {"note": "hi"})
    loaded = load_file(out)
    assert all(torch.equal(loaded[k], v) for k, v in t.items())
    with safe_open(out, "pt") as f:
        assert f.metadata() == {"note": "hi"}
    c = Checkpoint(out)
    assert c.keys() == list(t) and c.sha256() == file_sha256(out)
    assert c.specs["a.bias"].dtype == "BF16" and c.specs["a.weight"].shape == (64, 64)
    assert all(torch.equal(c.get(k), v) for k, v in t.items())


def test_sharded_layout_and_index(tmp_path):
    t = _tensors()
    out = tmp_path / "ckpt"
    write_checkpoint(out, t, {"note": "hi"}, max_shard_bytes=10_000)
    index = json.loads((out / INDEX_NAME).read_text())
    assert set(index["weight_map"]) == set(t)
    assert index["metadata"]["total_size"] == sum(v.numel() * v.element_size() for v in t.values())
    assert len(set(index["weight_map"].values())) == len(list(out.glob("model-*.safetensors"))) > 1
    c = Checkpoint(out)
    assert c.metadata["note"] == "hi" and set(c.keys()) == set(t)
    assert all(torch.equal(c.get(k), v) for k, v in t.items())
    # everything in one shard -> a plain model.safetensors, still readable as a directory
    write_checkpoint(tmp_path / "small", t)
    assert [p.name for p in (tmp_path / "small").iterdir()] == ["model.safetensors"]
    assert set(Checkpoint(tmp_path / "small").keys()) == set(t)


def test_writer_failure_leaves_nothing(tmp_path):
    t = _tensors()
    for out in (tmp_path / "x.safetensors", tmp_path / "dir"):
        with (
            pytest.raises(RuntimeError),
            ShardedWriter(out, {k: (v.dtype, v.shape) for k, v in t.items()}) as w,
        ):
            w.write("a.weight", t["a.weight"])
            raise RuntimeError("boom")
        with (
            pytest.raises(CheckpointError, match="closed after"),
            ShardedWriter(out, {k: (v.dtype, v.shape) for k, v in t.items()}) as w,
        ):
            w.write("a.weight", t["a.weight"])
    assert list(tmp_path.iterdir()) == []


def test_writer_checks_order_shape_and_refuses_overwrite(tmp_path):
    t = _tensors()
    specs = {k: (v.dtype, v.shape) for k, v in t.items()}
    with (
        pytest.raises(CheckpointError, match="expected tensor 'a.weight'"),
        ShardedWriter(tmp_path / "x.safetensors", specs) as w,
    ):
        w.write("a.bias", t["a.bias"])
    with (
        pytest.raises(CheckpointError, match="declared"),
        ShardedWriter(tmp_path / "x.safetensors", specs) as w,
    ):
        w.write("a.weight", t["a.weight"].double())
    write_checkpoint(tmp_path / "x.safetensors", t)
    with pytest.raises(FileExistsError):
        write_checkpoint(tmp_path / "x.safetensors", t)
    write_checkpoint(tmp_path / "x.safetensors", {"z": torch.zeros(1)}, overwrite=True)
    assert Checkpoint(tmp_path / "x.safetensors").keys() == ["z"]


def test_index_naming_a_tensor_absent_from_its_shard(tmp_path):
    out = tmp_path / "ckpt"
    write_checkpoint(out, _tensors(), max_shard_bytes=10_000)
    index = json.loads((out / INDEX_NAME).read_text())
    index["weight_map"]["ghost.weight"] = next(iter(index["weight_map"].values()))
    (out / INDEX_NAME).write_text(json.dumps(index))
    with pytest.raises(CheckpointError, match="ghost.weight"):
        Checkpoint(out)


def test_not_a_checkpoint(tmp_path):
    with pytest.raises(CheckpointError, match="no such"):
        Checkpoint(tmp_path / "nope.safetensors")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError, match="neither"):
        Checkpoint(tmp_path / "empty")
    (tmp_path / "junk.safetensors").write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00not json at all!")
    with pytest.raises(CheckpointError, match="corrupt"):
        Checkpoint(tmp_path / "junk.safetensors")
