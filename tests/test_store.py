"""The content-addressed store: ids, idempotence, verification, bad ids and paths, fsspec memory://."""

import hashlib
import json
import os
import shutil
import uuid

import pytest

from capvector.artifacts.errors import (
    AmbiguousId,
    ArtifactNotFound,
    CorruptArtifact,
    MalformedId,
    PathEscape,
    UnknownParent,
)
from capvector.artifacts.hashing import hash_file, manifest_id
from capvector.artifacts.provenance import code_version, installed_versions
from capvector.artifacts.records import SEAL_FIELD, RunRecord, metadata_digest
from capvector.artifacts.store import ArtifactStore


@pytest.fixture
def store(tmp_path):
    return ArtifactStore(tmp_path / "store", cache_dir=tmp_path / "cache")


def write(path, data: bytes):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


def test_file_id_is_sha256_and_sidecar_describes_it(store, tmp_path):
    src = write(tmp_path / "ckpt.safetensors", b"weights" * 1000)
    rec = store.put_file(src, "checkpoint", "pt", {"lr": 1e-3}, library_versions={"torch": "2.13"})
    assert rec.id == hashlib.sha256(src.read_bytes()).hexdigest() == hash_file(str(src))
    assert rec.layout == "file" and rec.files[0].path == "ckpt.safetensors" and rec.size == 7000
    sidecar = json.loads(open(store.sidecar_path(rec.id)).read())
    assert sidecar["kind"] == "checkpoint" and sidecar["config"] == {"lr": 1e-3}
    assert sidecar["library_versions"] == {"torch": "2.13"} and sidecar["code_version"]
    assert sidecar["format"] == 2 and sidecar[SEAL_FIELD] == metadata_digest(sidecar) == rec.metadata_sha256
    assert store.path(rec.id).read_bytes() == src.read_bytes()
    assert os.listdir(os.path.join(store.root, "tmp")) == []


def test_put_is_idempotent(store, tmp_path):
    src = write(tmp_path / "a.bin", b"same")
    first = store.put_file(src, "dataset", "first")
    again = store.put_bytes(b"same", "dataset", "second", filename="a.bin")
    assert again.id == first.id and again.name == "first"
    assert list(store.iter_ids()) == [first.id]


def test_directory_id_is_canonical_manifest(store, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    write(a / "model-00001.safetensors", b"one")
    write(a / "sub" / "index.json", b"{}")
    write(b / "sub" / "index.json", b"{}")  # created in the other order
    write(b / "model-00001.safetensors", b"one")
    ra, rb = store.put_dir(a, "checkpoint", "a"), store.put_dir(b, "checkpoint", "b")
    assert ra.id == rb.id
    entries = [(f.path, f.size, f.sha256) for f in ra.files]
    assert ra.id == manifest_id(entries)
    assert {f.path for f in ra.files} == {"model-00001.safetensors", "sub/index.json"}
    assert store.path(ra.id, member="sub/index.json").read_bytes() == b"{}"
    assert store.path(ra.id).is_dir()
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no files"):
        store.put_dir(tmp_path / "empty", "dataset", "x")


def test_prefixes_and_bad_ids(store):
    rec = store.put_bytes(b"x", "report", "r")
    assert store.get(rec.id[:6]).id == rec.id == store.resolve(rec.id.upper()[:10])
    for bad in ["", "abc", "zzzzzzzz", rec.id + "0", "../../etc"]:
        with pytest.raises(MalformedId):
            store.get(bad)
    other = "0" * 64 if not rec.id.startswith("0") else "f" * 64
    with pytest.raises(ArtifactNotFound):
        store.get(other)
    with pytest.raises(ArtifactNotFound):
        store.get(other[:8])
    # Two ids sharing a 6-character prefix are astronomically rare by chance; plant a second sidecar.
    twin = rec.id[:6] + ("0" * 58 if rec.id[6] != "0" else "1" * 58)
    shutil.copy(store.sidecar_path(rec.id), store.sidecar_path(twin))
    with pytest.raises(AmbiguousId) as err:
        store.get(rec.id[:6])
    assert rec.id in str(err.value) and twin in str(err.value)
    assert store.get(rec.id[:7]).id == rec.id


def test_paths_cannot_escape(store, tmp_path):
    rec = store.put_dir(write(tmp_path / "d" / "f.txt", b"hi").parent, "dataset", "d")
    for member in ["../../x", "/etc/passwd", "a/../../b", "..", ""]:
        with pytest.raises(PathEscape):
            store.path(rec.id, member=member)
    with pytest.raises(PathEscape):
        store.put_bytes(b"x", "report", "r", filename="../evil")
    with pytest.raises(PathEscape):
        store.put_run(RunRecord(flow_run_id="../../evil", flow_name="f"))
    # A tampered sidecar pointing outside the artifact is reported as corruption, never followed,
    # whether its seal was left broken or recomputed.
    sidecar = store.sidecar_path(rec.id)
    doc = json.loads(open(sidecar).read())
    doc["files"][0]["path"] = "../../../../etc/passwd"
    open(sidecar, "w").write(json.dumps(doc))
    with pytest.raises(CorruptArtifact, match=rec.id):
        store.path(rec.id)
    doc[SEAL_FIELD] = metadata_digest(doc)
    open(sidecar, "w").write(json.dumps(doc))
    with pytest.raises(CorruptArtifact, match=rec.id):
        store.path(rec.id)


def test_truncated_and_corrupted_content_is_detected(store, tmp_path):
    rec = store.put_file(write(tmp_path / "v.bin", b"0123456789" * 100), "vector", "v")
    obj = store.path(rec.id)
    with open(obj, "r+b") as f:  # same size, one byte flipped, mtime restored: only a hash sees it
        st = os.stat(obj)
        f.write(b"X")
    os.utime(obj, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert store.path(rec.id, verify=False) == obj  # the size+mtime check alone is blind to it
    with pytest.raises(CorruptArtifact, match=rec.id):
        store.path(rec.id)  # reads verify by default
    with pytest.raises(CorruptArtifact, match=rec.id):
        store.path(rec.id, verify=True)
    with pytest.raises(CorruptArtifact, match=rec.id):
        store.read_bytes(rec.id)  # small reads always hash
    os.truncate(obj, 10)  # size differs from the record: always re-hashed, never served
    with pytest.raises(CorruptArtifact, match=rec.id):
        store.path(rec.id)
    os.remove(obj)
    with pytest.raises(CorruptArtifact, match="missing"):
        store.path(rec.id)


def test_touched_file_is_rehashed_once_then_trusted(store, tmp_path):
    rec = store.put_file(write(tmp_path / "c.bin", b"c" * 100), "checkpoint", "c")
    obj = store.path(rec.id)
    os.utime(obj, ns=(1, 1))
    store.path(rec.id)  # re-hashes, content intact, records the new mtime
    assert store.get(rec.id).files[0].mtime_ns == 1


def test_unknown_parent_writes_nothing(store):
    parent = store.put_bytes(b"p", "dataset", "p")
    missing = "ab" * 32
    with pytest.raises(UnknownParent, match=missing):
        store.put_bytes(b"child", "checkpoint", "c", parents=[(parent.id, "data"), (missing, "base")])
    assert list(store.iter_ids()) == [parent.id]
    staging = os.path.join(store.root, "tmp")
    assert not os.path.exists(staging) or os.listdir(staging) == []
    child = store.put_bytes(b"child", "checkpoint", "c", parents=[(parent.id[:8], "data", {"split": "t"})])
    assert child.parents[0].id == parent.id and child.parents[0].attrs == {"split": "t"}


def test_deleted_object_is_restored_by_putting_it_again(store, tmp_path):
    rec = store.put_bytes(b"z" * 50, "report", "z")
    shutil.rmtree(store.object_path(rec.id))
    with pytest.raises(CorruptArtifact):
        store.path(rec.id)
    store.put_bytes(b"z" * 50, "report", "z")
    assert store.path(rec.id).read_bytes() == b"z" * 50


def test_gc_removes_only_uncommitted_garbage(store):
    keep = store.put_bytes(b"keep", "report", "k")
    orphan = os.path.join(store.root, "objects", "ee", "e" * 64)  # object renamed in, sidecar never written
    os.makedirs(orphan)
    open(os.path.join(orphan, "f"), "wb").close()
    staging = os.path.join(store.root, "tmp", uuid.uuid4().hex)
    os.makedirs(staging)
    young = store.gc()
    assert (young.removed, young.quarantined) == ([], [])  # too young: could be a write in progress
    result = store.gc(older_than_s=0)
    assert result.removed == [staging]
    # An object without a sidecar may be an artifact whose sidecar was lost: moved aside, never deleted.
    assert [os.path.basename(p) for p in result.quarantined] == ["e" * 64]
    assert not os.path.exists(orphan) and os.path.isfile(os.path.join(result.quarantined[0], "f"))
    assert list(store.iter_ids()) == [keep.id] and store.path(keep.id).read_bytes() == b"keep"


def test_memory_filesystem(tmp_path):
    store = ArtifactStore(f"memory://capvector-test-{uuid.uuid4().hex}", cache_dir=tmp_path / "cache")
    rec = store.put_bytes(b"hello" * 100, "dataset", "d", {"n": 1})
    dsrc = tmp_path / "adapter"
    write(dsrc / "adapter_model.safetensors", b"lora")
    write(dsrc / "adapter_config.json", b'{"r": 4}')
    drec = store.put_dir(dsrc, "adapter", "lora", parents=[(rec.id, "data")])
    ev = store.put_json({"b": 1, "a": [1, 2]}, "evaluation", "e", parents=[(drec.id[:6], "checkpoint")])
    assert store.get(rec.id[:6]).name == "d"
    assert sorted(store.iter_ids()) == sorted([rec.id, drec.id, ev.id])
    local = store.path(rec.id)
    assert str(local).startswith(str(tmp_path / "cache")) and local.read_bytes() == b"hello" * 100
    assert (store.path(drec.id) / "adapter_config.json").read_bytes() == b'{"r": 4}'
    assert store.open_json(ev.id) == {"a": [1, 2], "b": 1}
    store.put_run(RunRecord(flow_run_id="run-1", flow_name="pipeline"))
    assert [r.flow_run_id for r in store.iter_runs()] == ["run-1"]
    # Corrupt the remote copy: size differs, so the cached copy is not trusted and the download fails.
    store.fs.pipe_file(f"{store.object_path(rec.id)}/data.bin", b"evil")
    with pytest.raises(CorruptArtifact, match=rec.id):
        store.path(rec.id)
    with pytest.raises(CorruptArtifact, match=rec.id):
        store.read_bytes(rec.id)


def test_provenance_helpers():
    versions = installed_versions(["pydantic", "surely-not-installed-dist"])
    assert versions["pydantic"] and versions["surely-not-installed-dist"] is None
    assert code_version()
