"""The vector commands read every byte once: an outside input is hashed as the computation reads it,
and copied into the store's staging area from those same bytes; a stored input is checked by the hashes
taken while it is read; the output is committed by a rename. Bytes that changed, a symlink swapped in,
a failure: nothing registered. And no torch: importing it would cost a command more than streaming a
checkpoint."""

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file

from capvector.artifacts import store as store_mod
from capvector.artifacts.errors import CorruptArtifact
from capvector.core.vectors import safetensors_io, vector_ops
from capvector.core.vectors.safetensors_io import Checkpoint, CheckpointError
from capvector.core.vectors.vector_ops import VectorOpError
from capvector.tasks import vector_commands
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.vector_commands import extract_cli, merge_cli, stats_cli

REPO = Path(__file__).resolve().parent.parent
SHAPES = {"a.weight": (64, 32), "a.bias": (64,), "b.weight": (16, 64)}


def _checkpoint(folder: Path, name: str, seed: int, scale: float = 1.0) -> Path:
    g = torch.Generator().manual_seed(seed)
    path = folder / f"{name}.safetensors"
    save_file({k: scale * torch.randn(s, generator=g) for k, s in SHAPES.items()}, str(path))
    return path


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _rot(path: Path) -> None:
    """Flip the last byte (the top of the last float), times kept: bit rot."""
    st = os.stat(path)
    with open(path, "r+b") as f:
        f.seek(-1, os.SEEK_END)
        byte = f.read(1)
        f.seek(-1, os.SEEK_END)
        f.write(bytes([byte[0] ^ 0x7F]))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))


@pytest.fixture
def user(tmp_path):
    folder = tmp_path / "user"
    folder.mkdir()
    paths = {n: _checkpoint(folder, n, s) for n, s in (("pt", 0), ("ft", 1), ("ao", 2))}
    return Workspace(str(tmp_path / "home")), folder, paths


def _ids(workspace: Workspace) -> set[str]:
    return set(workspace.api.store.iter_ids())


def _staging_left(workspace: Workspace) -> list[str]:
    return os.listdir(workspace.api.store._p("tmp"))


def test_an_outside_input_is_read_and_hashed_once(user, monkeypatch):
    """Before: hashed on import, again by the verified read, again while streaming (and the output
    copied into the store and hashed once more)."""
    workspace, folder, p = user
    hashed: list[str] = []

    def spy(module, name):
        real = getattr(module, name)

        def wrapper(*args, **kw):
            hashed.append(Path(getattr(args[0], "name", args[0])).name)
            return real(*args, **kw)

        monkeypatch.setattr(module, name, wrapper)

    for module, name in [(store_mod, "hash_file"), (store_mod, "_hash_local"), (store_mod, "hash_stream"),
                         (store_mod, "copy_and_hash"), (safetensors_io, "file_sha256"),
                         (vector_commands, "hash_file")]:  # fmt: skip
        spy(module, name)
    read: dict[str, int] = {}
    real_read = vector_ops._read

    def counting_read(path, copy, offset, out):
        read[path.name] = read.get(path.name, 0) + out.size
        return real_read(path, copy, offset, out)

    monkeypatch.setattr(vector_ops, "_read", counting_read)
    out = folder / "gamma.safetensors"
    record = extract_cli(workspace, str(p["ao"]), str(p["ft"]), out, None, None, None)

    sizes = {n: p[n[:2]].stat().st_size for n in ("ao.safetensors", "ft.safetensors")}
    assert read == sizes  # every byte of each input read once (through its copy)
    assert hashed == ["gamma.safetensors"]  # the output, once; the inputs only as they were read
    parents = {r.role: r.id for r in record.parents}
    assert parents == {"minuend": _sha(p["ao"]), "subtrahend": _sha(p["ft"])}
    assert record.id == _sha(out)
    for role, src in (("minuend", p["ao"]), ("subtrahend", p["ft"])):
        stored = workspace.api.store.path(parents[role], verify=False)
        assert os.stat(stored).st_ino != os.stat(src).st_ino  # a copy, never a link to the user's file
    assert workspace.api.store.audit(record.id).status == "ok"
    assert _staging_left(workspace) == []


def test_a_stored_input_changed_after_import_is_refused(user):
    workspace, folder, p = user
    gamma = extract_cli(workspace, str(p["ao"]), str(p["ft"]), folder / "g.safetensors", None, None, None)
    ao = next(r.id for r in gamma.parents if r.role == "minuend")
    _rot(workspace.api.store.path(ao, verify=False))
    before = _ids(workspace)
    with pytest.raises(CorruptArtifact, match=ao):
        extract_cli(workspace, ao, str(p["ft"]), folder / "g2.safetensors", None, None, None)
    _rot(workspace.api.store.path(gamma.id, verify=False))
    with pytest.raises(CorruptArtifact, match=gamma.id):
        merge_cli(workspace, str(p["pt"]), [(gamma.id, 1.1)], folder / "m.safetensors", None, None, False)
    with pytest.raises(CorruptArtifact, match=gamma.id):
        stats_cli(workspace, gamma.id, None, None)
    assert _ids(workspace) == before  # θ_pt and θ_ft were fine, but nothing was made from them
    assert sorted(x.name for x in folder.iterdir()) == ["ao.safetensors", "ft.safetensors", "g.safetensors",
                                                        "pt.safetensors"]  # fmt: skip
    assert _staging_left(workspace) == []


def test_a_stored_input_changed_while_it_is_read_is_refused(user, monkeypatch):
    workspace, folder, p = user
    gamma = extract_cli(workspace, str(p["ao"]), str(p["ft"]), folder / "g.safetensors", None, None, None)
    stored = workspace.api.store.path(gamma.id, verify=False)
    real_read = vector_ops._read
    done = []

    def read_then_rot(path, copy, offset, out):
        buf = real_read(path, copy, offset, out)
        if path == stored and offset > 0 and not done:
            done.append(1)
            with open(stored, "r+b") as f:  # another writer, in the middle of the read
                f.seek(-1, os.SEEK_END)
                f.write(b"\x7f")
        return buf

    monkeypatch.setattr(vector_ops, "_read", read_then_rot)
    before = _ids(workspace)
    with pytest.raises((CorruptArtifact, VectorOpError), match=f"{gamma.id}|changed while"):
        merge_cli(workspace, str(p["pt"]), [(gamma.id, 1.1)], folder / "m.safetensors", None, None, False)
    assert _ids(workspace) == before and not (folder / "m.safetensors").exists()


def test_a_symlink_swapped_for_a_stored_input_is_refused(user, tmp_path):
    workspace, folder, p = user
    gamma = extract_cli(workspace, str(p["ao"]), str(p["ft"]), folder / "g.safetensors", None, None, None)
    stored = workspace.api.store.path(gamma.id, verify=False)
    stored.unlink()
    stored.symlink_to(folder / "g.safetensors")  # the same bytes, in a file the store does not own
    with pytest.raises(CorruptArtifact, match="not a regular file"):
        merge_cli(workspace, str(p["pt"]), [(gamma.id, 1.1)], folder / "m.safetensors", None, None, False)


def test_an_identical_input_already_stored_is_registered_again_from_the_fresh_copy(user):
    """`merge --vector gamma.safetensors` after `extract -o gamma.safetensors`: the same id, repaired."""
    workspace, folder, p = user
    out = folder / "g.safetensors"
    gamma = extract_cli(workspace, str(p["ao"]), str(p["ft"]), out, None, None, None)
    _rot(workspace.api.store.path(gamma.id, verify=False))
    merged = merge_cli(workspace, str(p["pt"]), [(str(out), 1.1)], folder / "m.sft", None, None, False)
    assert {r.role: r.id for r in merged.parents}["vector"] == gamma.id
    assert workspace.api.store.audit(gamma.id).status == "ok"  # the fresh bytes replaced the rotted ones


def test_a_failed_command_leaves_nothing_in_the_staging_area(user):
    workspace, folder, p = user
    bad = folder / "nan.safetensors"
    tensors = {k: torch.zeros(s) for k, s in SHAPES.items()}
    tensors["b.weight"][0, 0] = float("nan")
    save_file(tensors, str(bad))
    with pytest.raises(VectorOpError, match="NaN"):
        extract_cli(workspace, str(bad), str(p["ft"]), folder / "g.safetensors", None, None, None)
    assert _ids(workspace) == set() and _staging_left(workspace) == []


def test_sharded_outputs_and_inputs_go_through_the_staging_area(user):
    workspace, folder, p = user
    sharded = folder / "ao_sharded"
    tensors = {k: Checkpoint(p["ao"]).get(k) for k in SHAPES}
    safetensors_io.write_checkpoint(sharded, tensors, max_shard_bytes=9000)
    assert len(Checkpoint(sharded).files) > 1
    record = extract_cli(workspace, str(sharded), str(p["ft"]), folder / "gamma", None, None, None)
    stored = workspace.api.store.get(next(r.id for r in record.parents if r.role == "minuend"))
    assert stored.layout == "dir" and {f.path for f in stored.files} == {x.name for x in sharded.iterdir()}
    assert {f.path for f in workspace.api.store.get(record.id).files} == {
        x.name for x in (folder / "gamma").iterdir()
    }
    assert workspace.api.store.audit(stored.id).status == workspace.api.store.audit(record.id).status == "ok"
    assert _staging_left(workspace) == []


def test_vector_commands_work_on_a_remote_store(tmp_path, monkeypatch):
    import uuid

    monkeypatch.setenv("CAPVECTOR_CACHE", str(tmp_path / "cache"))
    folder = tmp_path / "user"
    folder.mkdir()
    p = {n: _checkpoint(folder, n, s) for n, s in (("pt", 0), ("ft", 1), ("ao", 2))}
    workspace = Workspace(f"memory://capvector-{uuid.uuid4().hex}")
    gamma = extract_cli(workspace, str(p["ao"]), str(p["ft"]), folder / "g.safetensors", None, None, None)
    pt = gamma.parents[0].id
    merged = merge_cli(workspace, pt, [(gamma.id, 1.1)], folder / "m.safetensors", None, None, False)
    assert merged.id == _sha(folder / "m.safetensors") and gamma.id == _sha(folder / "g.safetensors")
    assert workspace.api.store.audit(merged.id).status == "ok"


def test_vector_commands_do_not_import_torch(user):
    workspace, folder, p = user
    code = f"""
import sys
sys.path.insert(0, {str(REPO)!r})
from pathlib import Path
from capvector.tasks.vector_commands import extract_cli, merge_cli
from capvector.tasks.runtime.workspace import Workspace
ws, folder = Workspace({workspace.home!r}), Path({str(folder)!r})
g = extract_cli(ws, {str(p["ao"])!r}, {str(p["ft"])!r}, folder / "g.safetensors", None, None, None)
merge_cli(ws, {str(p["pt"])!r}, [(g.id, 1.1)], folder / "m.safetensors", None, None, False)
print("torch" in sys.modules)
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "False"


def test_inputs_read_in_and_out_of_storage_order_are_hashed_right(tmp_path, monkeypatch):
    """Reused read buffers, a hashing thread, a subtrahend stored in another order (hashed from disk)."""
    monkeypatch.setattr(vector_ops, "CHUNK_BYTES", 256)  # many chunks per tensor
    g = torch.Generator().manual_seed(0)
    a = {k: torch.randn(s, generator=g) for k, s in SHAPES.items()}
    b = {k: torch.randn(SHAPES[k], generator=g) for k in reversed(SHAPES)}
    pa, pb = tmp_path / "a.safetensors", tmp_path / "b.safetensors"
    safetensors_io.write_checkpoint(pa, a)
    safetensors_io.write_checkpoint(pb, b)
    assert Checkpoint(pa).keys() == list(reversed(Checkpoint(pb).keys()))
    hashes: dict[Path, str] = {}
    copies = {pa: tmp_path / "copies" / "a.safetensors", pb: tmp_path / "copies" / "b.safetensors"}
    out = vector_ops.extract(pa, pb, tmp_path / "g.safetensors", hashes=hashes, copies=copies)
    assert hashes == {pa: _sha(pa), pb: _sha(pb), copies[pa]: _sha(pa), copies[pb]: _sha(pb)}
    assert all(copies[p].read_bytes() == p.read_bytes() for p in (pa, pb))  # copied as read
    got = Checkpoint(out)
    assert all(torch.equal(got.get(k), a[k] - b[k]) for k in SHAPES)


def test_a_path_rewritten_between_its_check_and_its_read_is_refused(user, monkeypatch):
    workspace, folder, p = user
    real_locate = vector_commands.locate

    def locate_then_rewrite(workspace, ref, *args, **kw):
        item = real_locate(workspace, ref, *args, **kw)
        if ref == str(p["ft"]):  # the same tensors, another header: every offset moves
            tensors = {k: Checkpoint(p["ft"]).get(k) for k in SHAPES}
            p["ft"].unlink()
            save_file(tensors, str(p["ft"]), metadata={"note": "rewritten"})
        return item

    monkeypatch.setattr(vector_commands, "locate", locate_then_rewrite)
    with pytest.raises((CheckpointError, VectorOpError), match="changed while|ended while"):
        extract_cli(workspace, str(p["ao"]), str(p["ft"]), folder / "g.safetensors", None, None, None)
    assert _ids(workspace) == set() and not (folder / "g.safetensors").exists()


def test_an_input_named_twice_is_read_and_imported_once(user):
    workspace, folder, p = user
    twice = str(folder / "." / "ao.safetensors")  # another spelling of the same file
    record = extract_cli(workspace, str(p["ao"]), twice, folder / "z.safetensors", str(p["ao"]), None, None)
    roles = {r.role: r.id for r in record.parents}
    assert roles == dict.fromkeys(("minuend", "subtrahend", "base"), _sha(p["ao"]))
    assert all(not Checkpoint(folder / "z.safetensors").get(k).any() for k in SHAPES)
    assert _ids(workspace) == {_sha(p["ao"]), record.id}


def test_copies_go_through_user_space_where_the_kernel_cannot_copy(tmp_path, monkeypatch):
    """copy_file_range fails across filesystems (EXDEV): the copy is then written from the bytes read."""
    import errno

    def no_kernel_copy(*args):
        raise OSError(errno.EXDEV, "Invalid cross-device link")

    monkeypatch.setattr(os, "copy_file_range", no_kernel_copy)
    monkeypatch.setattr(vector_ops, "CHUNK_BYTES", 512)
    pa, pb = _checkpoint(tmp_path, "a", 0), _checkpoint(tmp_path, "b", 1)
    copies = {pa: tmp_path / "copies" / "a.safetensors", pb: tmp_path / "copies" / "b.safetensors"}
    hashes: dict[Path, str] = {}
    vector_ops.extract(pa, pb, tmp_path / "g.safetensors", hashes=hashes, copies=copies)
    assert all(copies[p].read_bytes() == p.read_bytes() for p in (pa, pb))
    assert hashes[copies[pa]] == _sha(pa) and hashes[copies[pb]] == _sha(pb)


def test_a_repeated_vector_stats_reuses_its_artifact(user):
    """Issue 37: `vector stats` called again on the same vector (by path or by id) registers nothing new
    and says that it reused its artifact; another base is other statistics, another artifact."""
    workspace, folder, p = user
    gamma = extract_cli(workspace, str(p["ao"]), str(p["ft"]), folder / "g.safetensors", None, None, None)
    rows, first, reused = stats_cli(workspace, gamma.id, None, None)
    assert rows and not reused and first.kind == "vector_stats"
    before = _ids(workspace)
    for ref in (gamma.id, str(folder / "g.safetensors"), gamma.id[:12]):
        _, again, reused = stats_cli(workspace, ref, None, None)
        assert again.id == first.id and reused
    assert _ids(workspace) == before
    _, with_base, reused = stats_cli(workspace, gamma.id, str(p["pt"]), None)
    assert with_base.id != first.id and not reused
