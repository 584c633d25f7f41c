"""The store's one-pass paths: staged content committed by a rename with the hashes its writer took,
kernel copies (never links), re-registration swapping fresh bytes in, reads checked by the hashes
taken while reading (`stream_path` + `check_read`), parents hashed while read not hashed again."""

import hashlib
import os

import pytest

from capvector.artifacts import store as store_mod
from capvector.artifacts.errors import CorruptArtifact
from capvector.artifacts.store import ArtifactStore, copy_file


@pytest.fixture
def store(tmp_path):
    return ArtifactStore(tmp_path / "store", cache_dir=tmp_path / "cache")


@pytest.fixture
def hashed(monkeypatch):
    """Paths the store hashes from disk (every whole-file hash it takes goes through one of these)."""
    seen: list[str] = []

    def spy(name):
        real = getattr(store_mod, name)

        def wrapper(*args, **k):
            names = [getattr(x, "name", x) for x in args]
            seen.append(next(os.path.basename(n) for n in names if isinstance(n, str | os.PathLike)))
            return real(*args, **k)

        monkeypatch.setattr(store_mod, name, wrapper)

    for name in ("hash_file", "_hash_local", "hash_stream", "copy_and_hash"):
        spy(name)
    return seen


def rot(path) -> None:
    """Flip the last byte, times kept (bit rot, a restore)."""
    st = os.stat(path)
    with open(path, "r+b") as f:
        f.seek(-1, os.SEEK_END)
        byte = f.read(1)
        f.seek(-1, os.SEEK_END)
        f.write(bytes([byte[0] ^ 0xFF]))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))


def test_copy_file_is_a_copy_never_a_link(tmp_path):
    src = tmp_path / "src.bin"
    src.write_bytes(b"weights" * 10_000)
    copy_file(src, tmp_path / "dst.bin")
    dst = tmp_path / "dst.bin"
    assert dst.read_bytes() == src.read_bytes()
    assert os.stat(dst).st_ino != os.stat(src).st_ino and os.stat(src).st_nlink == 1
    with open(src, "r+b") as f:  # a later edit of the user's file
        f.write(b"X")
    assert dst.read_bytes().startswith(b"weights")
    with pytest.raises(FileExistsError):  # never over an existing file
        copy_file(src, dst)
    with open(src, "rb") as f:  # an open file is copied from its start
        f.read(5)
        copy_file(f, tmp_path / "again.bin")
    assert (tmp_path / "again.bin").read_bytes() == src.read_bytes()


def test_a_staged_file_is_committed_by_a_rename_with_its_writers_hash(store, hashed):
    data = b"vector bytes" * 5000
    with store.staging() as stage:
        staged = stage / "gamma.safetensors"
        staged.write_bytes(data)
        inode = os.stat(staged).st_ino
        rec = store.put_file(staged, "vector", "gamma", sha256=hashlib.sha256(data).hexdigest())
        assert not staged.exists()  # moved, not copied
    assert hashed == []  # not read again
    path = store.path(rec.id, verify=False)
    assert os.stat(path).st_ino == inode and path.read_bytes() == data
    assert os.listdir(store._p("tmp")) == []  # nothing left in staging


def test_a_staged_file_without_a_hash_is_hashed_once(store, hashed):
    with store.staging() as stage:
        (stage / "x.bin").write_bytes(b"abc" * 1000)
        rec = store.put_file(stage / "x.bin", "dataset", "x")
    assert hashed == ["x.bin"] and rec.id == hashlib.sha256(b"abc" * 1000).hexdigest()


def test_a_staged_directory_is_committed_by_a_rename(store, hashed):
    with store.staging() as stage:
        d = stage / "ckpt"
        (d / "sub").mkdir(parents=True)
        (d / "a.bin").write_bytes(b"a" * 100)
        (d / "sub" / "b.bin").write_bytes(b"b" * 100)
        rec = store.put_dir(d, "checkpoint", "ckpt", hashes={"a.bin": hashlib.sha256(b"a" * 100).hexdigest()})
        assert not d.exists()
    assert hashed == ["b.bin"]  # only the member without a hash
    assert store.audit(rec.id).status == "ok"


def test_bytes_copied_in_must_be_those_the_caller_hashed(store, tmp_path):
    src = tmp_path / "x.bin"
    src.write_bytes(b"changed since it was read")
    with pytest.raises(ValueError, match="changed since it was hashed"):
        store.put_file(src, "checkpoint", "x", sha256=hashlib.sha256(b"what was read").hexdigest())
    assert list(store.iter_ids()) == []


def test_the_same_content_again_repairs_a_damaged_copy_without_reading_it(store, tmp_path, hashed):
    src = tmp_path / "pt.safetensors"
    src.write_bytes(b"weights" * 1000)
    rec = store.put_file(src, "checkpoint", "pt")
    rot(store.path(rec.id, verify=False))
    hashed.clear()
    again = store.put_file(src, "checkpoint", "other name")
    assert again.id == rec.id and again.name == "pt"  # the first registration's metadata stands
    assert hashed == ["pt.safetensors"]  # the fresh copy, once; the damaged one was never read
    assert store.audit(rec.id).status == "ok"


def test_the_same_directory_again_drops_planted_files(store, tmp_path):
    src = tmp_path / "ckpt"
    src.mkdir()
    (src / "a.bin").write_bytes(b"a" * 100)
    rec = store.put_dir(src, "checkpoint", "ckpt")
    planted = store.path(rec.id, verify=False) / "planted.bin"
    planted.write_bytes(b"x")
    assert store.audit(rec.id).status == "corrupt"
    store.put_dir(src, "checkpoint", "ckpt")
    assert not planted.exists() and store.audit(rec.id).status == "ok"


def test_a_symlinked_folder_never_leads_a_repair_outside_the_store(store, tmp_path):
    src = tmp_path / "ckpt"
    (src / "sub").mkdir(parents=True)
    (src / "sub" / "b.bin").write_bytes(b"b" * 100)
    rec = store.put_dir(src, "checkpoint", "ckpt")
    outside = tmp_path / "outside"
    outside.mkdir()
    obj = store.path(rec.id, verify=False)
    for f in (obj / "sub").iterdir():
        f.unlink()
    (obj / "sub").rmdir()
    (obj / "sub").symlink_to(outside, target_is_directory=True)
    store.put_dir(src, "checkpoint", "ckpt")
    assert list(outside.iterdir()) == []  # nothing written through the link
    assert store.audit(rec.id).status == "ok"


def test_stream_path_and_check_read_take_the_readers_hashes_and_refuse_other_bytes(store, tmp_path):
    src = tmp_path / "v.bin"
    src.write_bytes(b"vector" * 1000)
    rec = store.put_file(src, "vector", "v")
    path, record = store.stream_path(rec.id)
    assert record.id == rec.id and path.read_bytes() == src.read_bytes()
    assert store.check_read(record, path, {path: rec.id}) == {"v.bin": rec.id}
    with pytest.raises(CorruptArtifact, match=rec.id):  # what a reader of changed bytes hashed
        store.check_read(record, path, {path: hashlib.sha256(b"other").hexdigest()})
    rot(path)
    with pytest.raises(CorruptArtifact, match=rec.id):  # a file not hashed by the reader: hashed now
        store.check_read(record, path, {})


def test_a_symlink_in_place_of_a_stored_file_is_refused(store, tmp_path):
    src = tmp_path / "v.bin"
    src.write_bytes(b"vector" * 1000)
    rec = store.put_file(src, "vector", "v")
    path = store.path(rec.id, verify=False)
    twin = tmp_path / "twin.bin"  # the same bytes, but outside the store: a later edit would not show
    twin.write_bytes(src.read_bytes())
    path.unlink()
    path.symlink_to(twin)
    with pytest.raises(CorruptArtifact, match="not a regular file"):
        store.stream_path(rec.id)


def test_a_parent_hashed_while_read_is_not_hashed_again(store, hashed):
    parent = store.put_bytes(b"weights" * 100, "checkpoint", "p")
    hashed.clear()
    store.put_bytes(b"scores", "evaluation", "e", parents=[(parent.id, "checkpoint")],
                    parent_hashes={parent.id: {"data.bin": parent.id}})  # fmt: skip
    assert hashed == ["data.bin"]  # the child's own bytes as they were written; the parent not at all


def test_a_parent_whose_read_hash_differs_from_its_record_is_hashed_and_refused(store, hashed):
    parent = store.put_bytes(b"weights" * 100, "checkpoint", "p")
    rot(store.path(parent.id, verify=False))
    rotted = hashlib.sha256(store.path(parent.id, verify=False).read_bytes()).hexdigest()
    with pytest.raises(CorruptArtifact, match=parent.id):
        store.put_bytes(b"scores", "evaluation", "e", parents=[(parent.id, "checkpoint")],
                        parent_hashes={parent.id: {"data.bin": rotted}})  # fmt: skip
    assert list(store.iter_ids()) == [parent.id]
