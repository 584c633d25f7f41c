"""The streaming reader/writer: round trips, sharding, atomicity, header validation."""

import json
from pathlib import Path

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file

from capvector.core.vectors.safetensors_io import (
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


# ---------------------------------------------------------------------------- crafted headers
def write_raw(path, header, data: bytes = b"") -> None:
    """A safetensors file from a header (dict, or the JSON text as bytes) and data, with no checks."""
    text = header if isinstance(header, bytes) else json.dumps(header).encode()
    text += b" " * (-len(text) % 8)
    path.write_bytes(len(text).to_bytes(8, "little") + text + data)


def _f32(shape, begin, end):
    return {"dtype": "F32", "shape": shape, "data_offsets": [begin, end]}


_B = {"b": _f32([2], 8, 16)}  # a well-formed second tensor after a broken first one

# id -> (header, data, tensor the one-line error must name); the safetensors library refuses each.
MALFORMED = {
    "negative_offset": ({"a": _f32([2], -8, 0), "b": _f32([4], 0, 16)}, bytes(16), "a"),
    "overlapping_offsets": ({"a": _f32([2], 0, 8), "b": _f32([2], 4, 12)}, bytes(16), "b"),
    "hole_between_tensors": ({"a": _f32([2], 0, 8), "b": _f32([1], 12, 16)}, bytes(16), "b"),
    "first_tensor_not_at_zero": ({"a": _f32([2], 8, 16)}, bytes(16), "a"),
    "end_before_begin": ({"a": _f32([2], 0, 8), "b": _f32([2], 16, 8)}, bytes(16), "b"),
    "out_of_bounds": ({"a": _f32([2], 0, 8), "b": _f32([4], 8, 24)}, bytes(16), "b"),
    "length_not_dtype_times_shape": ({"a": _f32([3], 0, 8), **_B}, bytes(16), "a"),
    "missing_dtype": ({"a": {"shape": [2], "data_offsets": [0, 8]}, **_B}, bytes(16), "a"),
    "unknown_dtype": ({"a": {**_f32([2], 0, 8), "dtype": "X99"}, **_B}, bytes(16), "a"),
    "entry_not_an_object": ({"a": [1, 2], **_B}, bytes(16), "a"),
    "shape_not_a_list": ({"a": {**_f32([2], 0, 8), "shape": 2}, **_B}, bytes(16), "a"),
    "negative_dimension": ({"a": {**_f32([2], 0, 8), "shape": [-2]}, **_B}, bytes(16), "a"),
    "float_dimension": ({"a": {**_f32([2], 0, 8), "shape": [2.0]}, **_B}, bytes(16), "a"),
    "missing_shape": ({"a": {"dtype": "F32", "data_offsets": [0, 8]}, **_B}, bytes(16), "a"),
    "three_offsets": ({"a": {**_f32([2], 0, 8), "data_offsets": [0, 8, 9]}, **_B}, bytes(16), "a"),
    "string_offsets": ({"a": {**_f32([2], 0, 8), "data_offsets": ["0", "8"]}, **_B}, bytes(16), "a"),
    "missing_offsets": ({"a": {"dtype": "F32", "shape": [2]}, **_B}, bytes(16), "a"),
}
# id -> (header, data, what the one-line error must say); refused by the library, no single tensor at fault.
MALFORMED_FILE = {
    "bytes_after_last_tensor": ({"a": _f32([2], 0, 8)}, bytes(16), "after its last tensor"),
    "metadata_not_strings": ({"__metadata__": {"k": 1}, "a": _f32([2], 0, 8)}, bytes(8), "__metadata__"),
    "header_not_an_object": ([1, 2], b"", "not a JSON object"),
    "minus_zero_dimension": (b'{"a":{"dtype":"F32","shape":[-0],"data_offsets":[0,0]}}', b"", "safetensors"),
    "duplicate_metadata": (b'{"__metadata__":{},"__metadata__":null}', b"", "safetensors"),
}
# id -> (header, data); the library accepts these, so must we.
ACCEPTED = {
    "keys_not_in_offset_order": ({"b": _f32([2], 8, 16), "a": _f32([2], 0, 8)}, bytes(range(16))),
    "extra_field": ({"a": {**_f32([2], 0, 8), "extra": 1}}, bytes(range(8))),
    "null_metadata": ({"__metadata__": None, "a": _f32([2], 0, 8)}, bytes(range(8))),
    "empty_tensors_share_an_offset": ({"z": _f32([0], 0, 0), "a": _f32([2], 0, 8)}, bytes(range(8))),
    "no_tensors": ({}, b""),
    "leading_whitespace": (b'  {"a":{"dtype":"F32","shape":[],"data_offsets":[0,4]}}', bytes(4)),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_malformed_header_is_refused_in_one_line_naming_the_tensor(tmp_path, case):
    header, data, tensor = MALFORMED[case]
    path = tmp_path / f"{case}.safetensors"
    write_raw(path, header, data)
    with pytest.raises(Exception, match="Error while deserializing header"):
        safe_open(path, "pt").__enter__()  # the reference refuses it too
    with pytest.raises(CheckpointError) as err:
        Checkpoint(path)
    msg = str(err.value)
    assert "\n" not in msg and f"tensor {tensor!r}" in msg and str(path) in msg, msg


@pytest.mark.parametrize("case", list(MALFORMED_FILE))
def test_malformed_file_is_refused_in_one_line(tmp_path, case):
    header, data, needle = MALFORMED_FILE[case]
    path = tmp_path / f"{case}.safetensors"
    write_raw(path, header, data)
    with pytest.raises(Exception, match="Error while deserializing header"):
        safe_open(path, "pt").__enter__()
    with pytest.raises(CheckpointError) as err:
        Checkpoint(path)
    msg = str(err.value)
    assert "\n" not in msg and needle in msg and str(path) in msg, msg


@pytest.mark.parametrize("case", list(ACCEPTED))
def test_headers_the_library_accepts_are_read_as_it_reads_them(tmp_path, case):
    header, data = ACCEPTED[case]
    path = tmp_path / f"{case}.safetensors"
    write_raw(path, header, data)
    with safe_open(path, "pt") as f:
        want = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 (safe_open is not a Mapping)
    c = Checkpoint(path)
    assert set(c.keys()) == set(want)
    assert all(torch.equal(c.get(k), v) for k, v in want.items())


def test_header_length_beyond_the_file_is_reported_without_file_bytes(tmp_path):
    path = tmp_path / "x.safetensors"
    path.write_bytes((1000).to_bytes(8, "little") + b"{}")
    with pytest.raises(CheckpointError, match=r"header length 1000 exceeds file size 10\b"):
        Checkpoint(path)
    path.write_bytes(b"\xff\xfe" + b"x" * 20)  # bytes that are no header length at all
    with pytest.raises(CheckpointError) as err:
        Checkpoint(path)
    assert "\n" not in str(err.value)


# ---------------------------------------------------------------------------- shards stay inside
def _sharded_with_outside_copy(tmp_path):
    """A sharded checkpoint `ck/` and, outside it, `outside.safetensors`: a valid copy of its last shard."""
    write_checkpoint(tmp_path / "ck", _tensors(), max_shard_bytes=10_000)
    shard = Checkpoint(tmp_path / "ck").files[-1]
    outside = tmp_path / "outside.safetensors"
    outside.write_bytes(shard.read_bytes())
    return tmp_path / "ck", shard, outside


def _point_index(ck, old: str, new: str) -> None:
    index = json.loads((ck / INDEX_NAME).read_text())
    index["weight_map"] = {k: new if v == old else v for k, v in index["weight_map"].items()}
    (ck / INDEX_NAME).write_text(json.dumps(index))


@pytest.mark.parametrize("how", ["dotdot", "absolute", "symlink", "directory", "single_symlink"])
def test_shard_outside_the_checkpoint_folder_is_refused(tmp_path, how):
    ck, shard, outside = _sharded_with_outside_copy(tmp_path)
    name = shard.name
    if how == "dotdot":
        shard.unlink()
        name = "../outside.safetensors"
        _point_index(ck, shard.name, name)
    elif how == "absolute":
        shard.unlink()
        name = str(outside)
        _point_index(ck, shard.name, name)
    elif how == "symlink":
        shard.unlink()
        shard.symlink_to(outside)
    elif how == "directory":
        shard.unlink()
        shard.mkdir()
    else:  # a directory whose model.safetensors links out
        ck = tmp_path / "single"
        ck.mkdir()
        (ck / "model.safetensors").symlink_to(outside)
        name = "model.safetensors"
    with pytest.raises(CheckpointError) as err:
        Checkpoint(ck)
    msg = str(err.value)
    assert "\n" not in msg and repr(name) in msg, msg


def test_escaping_shard_is_refused_before_it_is_opened(tmp_path):
    """Nothing of a file outside the folder (here its first 8 bytes as an integer) may reach the error."""
    ck, shard, _ = _sharded_with_outside_copy(tmp_path)
    secret = tmp_path / "secret"
    secret.write_bytes(b"root:x:0:0:root:/root:/bin/bash\n")
    name = "../secret"
    _point_index(ck, shard.name, name)
    with pytest.raises(CheckpointError) as err:
        Checkpoint(ck)
    msg = str(err.value)
    assert repr(name) in msg and str(int.from_bytes(b"root:x:0", "little")) not in msg, msg


def test_shards_linked_or_nested_inside_the_folder_are_read(tmp_path):
    ck, shard, _ = _sharded_with_outside_copy(tmp_path)
    digest = Checkpoint(ck).sha256()
    (ck / "real").mkdir()
    shard.rename(ck / "real" / shard.name)
    shard.symlink_to(Path("real") / shard.name)  # a relative link that stays inside
    c = Checkpoint(ck)
    assert c.sha256() == digest and all(torch.equal(c.get(k), v) for k, v in _tensors().items())
    _point_index(ck, shard.name, f"real/{shard.name}")
    shard.unlink()
    assert all(torch.equal(Checkpoint(ck).get(k), v) for k, v in _tensors().items())


def test_sha256_tells_shards_in_different_subfolders_apart(tmp_path):
    """Shards sharing a base name in different subfolders must each count towards the content hash."""
    t = _tensors()
    for name, tensors in (("ck", t), ("other", {k: v if k != "a.weight" else v + 1 for k, v in t.items()})):
        ck = tmp_path / name
        write_checkpoint(ck, tensors, max_shard_bytes=10_000)
        c = Checkpoint(ck)
        for sub, f in (("x", c.files[0]), ("y", c.files[-1])):
            (ck / sub).mkdir()
            f.rename(ck / sub / "shard.safetensors")
            _point_index(ck, f.name, f"{sub}/shard.safetensors")
    assert Checkpoint(tmp_path / "ck").specs["a.weight"].file.parent.name == "x"
    assert Checkpoint(tmp_path / "ck").sha256() != Checkpoint(tmp_path / "other").sha256()


@pytest.mark.parametrize("change", [{"weight_map": {"a.weight": ["x"]}}, {"metadata": [1]}])
def test_index_that_is_not_a_name_map_is_refused(tmp_path, change):
    ck = tmp_path / "ck"
    write_checkpoint(ck, _tensors(), max_shard_bytes=10_000)
    index = json.loads((ck / INDEX_NAME).read_text())
    (ck / INDEX_NAME).write_text(json.dumps({**index, **change}))
    with pytest.raises(CheckpointError, match="unreadable index"):
        Checkpoint(ck)
