"""Issue 25, "Nothing wrong trusted, nothing lost": what the store and the catalogue must refuse to
read, believe or delete. Real store, real DuckDB catalogue, real CLI (typer's runner on the same app,
or the console entry point in a subprocess where the exit status and stderr line matter)."""

import json
import os
import re
import stat
from pathlib import Path

import duckdb
import pytest
import torch
from safetensors.torch import save_file
from typer.testing import CliRunner

from capvector.artifacts import catalogue as catalogue_mod
from capvector.artifacts import store as store_mod
from capvector.artifacts.api import ArtifactsAPI
from capvector.artifacts.errors import CorruptArtifact
from capvector.artifacts.records import SEAL_FIELD
from capvector.flows.cli.main import app

SHAPES = {"blocks.0.attn.weight": (6, 4), "blocks.1.mlp.weight": (3, 6)}


def cli(home, *args: str):
    return CliRunner().invoke(app, ["--home", str(home), *args])


def _sharded(folder: Path, seed: int = 0) -> Path:
    """A two-shard safetensors checkpoint with its index, as `capvector import` takes it."""
    gen = torch.Generator().manual_seed(seed)
    folder.mkdir(parents=True)
    weight_map = {}
    for i, (name, shape) in enumerate(SHAPES.items()):
        shard = f"model-{i + 1:05d}-of-00002.safetensors"
        save_file({name: torch.randn(shape, generator=gen)}, str(folder / shard))
        weight_map[name] = shard
    (folder / "model.safetensors.index.json").write_text(json.dumps({"weight_map": weight_map}))
    return folder


def _tree(root: Path) -> dict[str, tuple]:
    """Every path under `root` with its type, size, mtime and (for files) bytes: to prove nothing changed."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            st = os.lstat(p)
            data = p.read_bytes() if stat.S_ISREG(st.st_mode) else None
            out[str(p.relative_to(root))] = (stat.S_IFMT(st.st_mode), st.st_size, st.st_mtime_ns, data)
    return out


# ---------------------------------------------------------------------------- 8: names are one line
FORGED = "pt\n└── (init) checkpoint evil [000000000000]"


def test_a_name_with_a_newline_is_refused_at_registration(tmp_path):
    home = tmp_path / "home"
    ckpt = tmp_path / "pt.safetensors"
    save_file({"w": torch.ones(2, 2)}, str(ckpt))
    result = cli(home, "import", str(ckpt), "--name", FORGED)
    assert result.exit_code != 0
    assert isinstance(result.exception, ValueError)
    assert "U+000A" in str(result.exception) and "single printable line" in str(result.exception)
    api = ArtifactsAPI(str(home))
    assert list(api.store.iter_ids()) == []  # nothing stored
    for bad in ("a\rb", "a\x1b[31mb", "a\u202eb", "a\u2028b"):
        with pytest.raises(ValueError, match="control character"):
            api.store.put_bytes(b"x", "checkpoint", bad)
    with pytest.raises(ValueError, match="kind"):
        api.store.put_bytes(b"x", "check\npoint", "ok")
    parent = api.store.put_bytes(b"p", "checkpoint", "p").id
    with pytest.raises(ValueError, match="role"):
        api.store.put_bytes(b"y", "checkpoint", "ok", parents=[(parent, "a\nb")])


def test_an_existing_name_with_a_newline_is_escaped_in_every_view(tmp_path, monkeypatch):
    """A record written before the check (simulated by switching it off) cannot forge a tree line."""
    home = tmp_path / "home"
    api = ArtifactsAPI(str(home))
    monkeypatch.setattr(store_mod, "_check_labels", lambda kind, name: None)
    pt = api.register_json({"w": 1}, "checkpoint", FORGED).id
    child = api.register_json({"w": 2}, "checkpoint", "ft", parents=[(pt, "init")]).id
    monkeypatch.undo()

    tree = cli(home, "lineage", child)
    assert tree.exit_code == 0, tree.output
    lines = tree.output.splitlines()
    assert len(lines) == 2, tree.output  # the root and its one real parent: no forged `(init)` line
    assert "evil" in lines[1] and "\\n" in lines[1] and lines[1].startswith("└── (init) checkpoint pt\\n")
    mermaid = cli(home, "lineage", child, "--format", "mermaid")
    assert mermaid.exit_code == 0
    drawn = [line for line in mermaid.output.splitlines() if not line.strip().startswith("class")]
    assert len(drawn) == 2 and "pt\\n" in mermaid.output  # the graph line and the one edge


# ---------------------------------------------------------------------------- 1: folder imports
def _plant(folder: Path, how: str) -> str:
    """Put something that is not the checkpoint into an import folder; returns its member name."""
    if how == "symlink out":
        (folder / "notes.txt").symlink_to("/etc/passwd")
        return "notes.txt"
    if how == "fifo":
        os.mkfifo(folder / "pipe")
        return "pipe"
    if how == "device link":
        (folder / "zeros.bin").symlink_to("/dev/zero")
        return "zeros.bin"
    (folder / "sub").mkdir()
    (folder / "sub" / "link").symlink_to("../../outside.txt")  # relative, leading out of the folder
    (folder.parent / "outside.txt").write_text("secret")
    return "sub/link"


@pytest.mark.parametrize("how", ["symlink out", "fifo", "device link", "relative link out"])
def test_a_folder_import_reads_only_regular_files_inside_the_folder(tmp_path, how):
    from conftest import run_cli

    home, folder = tmp_path / "home", _sharded(tmp_path / "ckpt")
    member = _plant(folder, how)
    # The console entry point in a subprocess with a deadline: a FIFO must not hang the import.
    result = run_cli("import", str(folder), home=home, check=False, timeout=120)
    assert result.returncode == 2, (result.stdout, result.stderr)
    line = result.stderr.strip()
    assert len(line.splitlines()) == 1 and member in line and "regular file" in line, line
    assert "root:" not in result.stderr + result.stdout  # /etc/passwd's bytes are never echoed
    store = ArtifactsAPI(str(home)).store
    assert list(store.iter_ids()) == []  # nothing stored
    objects = Path(store.root) / "objects"
    assert not any(p.is_file() for p in objects.rglob("*")) and not any(Path(store.root, "tmp").glob("*"))


def test_a_link_inside_the_folder_is_stored_as_its_content(tmp_path):
    home, folder = tmp_path / "home", _sharded(tmp_path / "ckpt")
    (folder / "README.md").write_text("a model card")
    (folder / "card.md").symlink_to("README.md")
    result = cli(home, "import", str(folder))
    assert result.exit_code == 0, result.output
    record = ArtifactsAPI(str(home)).store.get(result.output.strip())
    assert {"README.md", "card.md"} <= {f.path for f in record.files}


def test_a_member_that_grows_while_it_is_copied_is_refused(tmp_path, monkeypatch):
    """The copy of each member is bounded by the size it was listed with."""
    store = store_mod.ArtifactStore(tmp_path / "store", cache_dir=tmp_path / "cache")
    folder = tmp_path / "d"
    folder.mkdir()
    (folder / "log.txt").write_bytes(b"x" * 10)
    real = store_mod._open_member

    def open_then_grow(full, rel, src_dir):
        f, size = real(full, rel, src_dir)
        with open(full, "ab") as out:
            out.write(b"y" * 100)  # another writer appends after the file was listed and opened
        return f, size

    monkeypatch.setattr(store_mod, "_open_member", open_then_grow)
    with pytest.raises(ValueError, match="log.txt .* changed while it was being stored"):
        store.put_dir(folder, "dataset", "d")
    assert list(store.iter_ids()) == []


# ---------------------------------------------------------------------------- 2: a stripped seal
def _downgrade(store, artifact_id: str, change) -> None:
    """Strip the seal, write `format: 1` and edit: what an old sidecar looks like, with forged metadata."""
    path = store.sidecar_path(artifact_id)
    doc = json.loads(Path(path).read_text())
    doc.pop(SEAL_FIELD)
    doc["format"] = 1
    change(doc)
    Path(path).write_text(json.dumps(doc, indent=1))


@pytest.fixture
def downgraded(tmp_path):
    """θ_pt -> child (role init); then the child's sidecar is downgraded with its edge dropped."""
    home = tmp_path / "home"
    api = ArtifactsAPI(str(home))
    pt = api.register_json({"w": 1}, "checkpoint", "pt").id
    child = api.register_json({"w": 2}, "checkpoint", "ft", {"lr": 0.1}, parents=[(pt, "init")]).id
    _downgrade(api.store, child, lambda d: d.update(parents=[], name="forged", config={"lr": 9}))
    return home, pt, child


def test_a_stripped_seal_is_refused_where_the_catalogue_knew_it_sealed(downgraded):
    home, pt, child = downgraded
    api = ArtifactsAPI(str(home))
    with pytest.raises(CorruptArtifact, match=f"{child}.*seal was stripped"):
        api.get(child)
    shown = cli(home, "artifacts", "show", child)
    assert shown.exit_code != 0 and "forged" not in shown.output
    with pytest.raises(CorruptArtifact, match=child):
        api.path(child)
    with pytest.raises(CorruptArtifact, match=child):
        api.register_json({"g": 1}, "report", "g", parents=[(child, "of")])


def test_a_rebuild_keeps_the_catalogue_row_over_a_stripped_seal(downgraded):
    home, pt, child = downgraded
    api = ArtifactsAPI(str(home))
    report = api.rebuild()
    assert child in report.corrupt and child in report.kept
    assert api.query("SELECT parent, child, role FROM edges").values.tolist() == [[pt, child, "init"]]
    assert api.query("SELECT name FROM artifacts WHERE id = ?", [child])["name"][0] == "ft"
    again = api.rebuild()  # the catalogue still knows it was sealed: a second rebuild trusts it no more
    assert child in again.kept and api.query("SELECT count(*) n FROM edges")["n"][0] == 1
    result = cli(home, "catalogue", "rebuild")
    assert result.exit_code == 1 and child in result.output and "kept" in result.output


def test_verify_fails_on_a_stripped_seal_and_names_unsealed_records(downgraded, tmp_path):
    home, pt, child = downgraded
    result = cli(home, "verify", "--all")
    assert result.exit_code == 1, result.output
    assert re.search(rf"CORRUPT\s+{child}.*seal was stripped", result.output), result.output
    # A record the catalogue never saw sealed (a genuinely old one) is reported as unsealed, by id.
    api = ArtifactsAPI(str(home))
    old = api.store.put_bytes(b"old", "checkpoint", "old").id  # not indexed yet
    _downgrade(api.store, old, lambda d: None)
    result = cli(home, "verify", old)
    assert result.exit_code == 0 and re.search(rf"UNSEALED\s+{old}", result.output), result.output
    assert cli(home, "verify", "--strict", old).exit_code == 1
    report = api.rebuild()  # indexed from the unsealed sidecar, and listed as such
    assert old in report.unsealed and old not in report.kept
    assert api.catalogue.recorded_sealed(old) is False and api.catalogue.recorded_sealed(pt) is True


# ---------------------------------------------------------------------------- 6: gc deletes nothing named
def test_gc_never_deletes_a_parent_whose_sidecar_was_lost(tmp_path):
    home = tmp_path / "home"
    api = ArtifactsAPI(str(home))
    pt = api.register_json({"pt": 0}, "checkpoint", "pt")
    children = [
        api.register_json({"w": i}, "checkpoint", f"c{i}", parents=[(pt.id, "init")]).id for i in range(6)
    ]
    weights = Path(api.store.path(pt.id))
    os.remove(api.store.sidecar_path(pt.id))  # θ_pt's sidecar is lost

    result = cli(home, "catalogue", "gc", "--older-than", "0")
    assert result.exit_code == 0, result.output
    assert weights.read_bytes() == json.dumps({"pt": 0}, sort_keys=True, indent=1).encode()
    assert "kept in place (named as a parent): 1" in result.output and pt.id in result.output
    api = ArtifactsAPI(str(home))
    assert api.query("SELECT name FROM artifacts WHERE id = ?", [pt.id])["name"].tolist() == ["pt"]
    assert len(api.query("SELECT * FROM edges WHERE parent = ?", [pt.id])) == len(children)


def test_gc_quarantines_an_orphan_without_a_sidecar_instead_of_deleting_it(tmp_path):
    home = tmp_path / "home"
    api = ArtifactsAPI(str(home))
    lone = api.register_json({"w": 7}, "checkpoint", "lone")
    os.remove(api.store.sidecar_path(lone.id))
    report = ArtifactsAPI(str(home)).gc(older_than_s=0)
    assert [os.path.basename(p) for p in report.quarantined] == [lone.id] and report.kept == []
    moved = Path(report.quarantined[0])
    assert moved.is_relative_to(home) and (moved / "data.json").read_bytes() == b'{\n "w": 7\n}'
    saved = json.loads(Path(str(moved) + ".catalogue-row.json").read_text())
    assert saved["artifact"]["name"] == "lone"  # its metadata, kept beside it before its row goes
    assert report.rows == [lone.id]
    assert not Path(api.store.object_path(lone.id)).exists()


# ---------------------------------------------------------------------------- 7: an unreadable catalogue
def _home_with_lineage(home: Path) -> tuple[str, str]:
    api = ArtifactsAPI(str(home))
    pt = api.register_json({"pt": 1}, "checkpoint", "pt").id
    child = api.register_json({"ft": 1}, "checkpoint", "ft", parents=[(pt, "init")]).id
    return pt, child


def _garbage(path: Path) -> None:
    path.write_bytes(os.urandom(1 << 16))


@pytest.mark.parametrize("command", [["catalogue", "rebuild"], ["artifacts", "list"], ["lineage"]])
def test_an_unreadable_catalogue_is_set_aside_and_rebuilt_from_the_store(tmp_path, command):
    from conftest import run_cli

    home = tmp_path / "home"
    pt, child = _home_with_lineage(home)
    catalogue = home / "catalogue.duckdb"
    _garbage(catalogue)
    damaged = catalogue.read_bytes()
    args = [*command, child] if command == ["lineage"] else command
    result = run_cli(*args, home=home, check=False, timeout=300)
    assert result.returncode == 0, result.stderr
    told = [line for line in result.stderr.splitlines() if "catalogue" in line]
    assert len(told) == 1 and "rebuilding it from the store" in told[0], result.stderr
    aside = list(home.glob("catalogue.duckdb.corrupt-*"))
    assert len(aside) == 1 and aside[0].read_bytes() == damaged  # kept for inspection
    if command == ["lineage"]:
        assert "(init) checkpoint pt" in result.stdout
    edges = ArtifactsAPI(str(home)).query("SELECT parent, child FROM edges").values.tolist()
    assert edges == [[pt, child]]


def test_a_catalogue_from_a_newer_duckdb_is_set_aside_and_rebuilt(tmp_path, monkeypatch, caplog):
    """DuckDB 2.0 checksums its header, so a file of another storage version cannot be forged here;
    the error such a file raises (from DuckDB's own wording) is raised on the first open instead."""
    home = tmp_path / "home"
    pt, child = _home_with_lineage(home)
    real, calls = catalogue_mod._attached_read, []

    def newer(path, fn):
        calls.append(path)
        if len(calls) == 1:
            raise duckdb.IOException(
                "IO Error: Trying to read a database file with version number 69, but we can only read "
                "versions between 64 and 68. The database file was created with a newer version of DuckDB."
            )
        return real(path, fn)

    monkeypatch.setattr(catalogue_mod, "_attached_read", newer)
    api = ArtifactsAPI(str(home))
    told = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(told) == 1 and "version number 69" in told[0] and "rebuilding it from the store" in told[0]
    assert len(list(home.glob("catalogue.duckdb.corrupt-*"))) == 1
    assert api.query("SELECT parent, child FROM edges").values.tolist() == [[pt, child]]


# ---------------------------------------------------------------------------- 12: a read-only home
def test_reading_works_on_a_home_this_process_may_not_write(tmp_path, monkeypatch):
    """Tests run as root, where chmod does not stop writes: the kernel's answer (`os.access`, which a
    read-only mount refuses even to root) is replaced by "not writable", and the whole home is
    compared byte for byte before and after: nothing in it may be written."""
    home = tmp_path / "home"
    pt, child = _home_with_lineage(home)
    ArtifactsAPI(str(home)).store.put_json(
        {"late": 1}, "report", "late", parents=[(child, "of")]
    )  # unindexed
    before = _tree(home)
    monkeypatch.setattr(catalogue_mod, "_writable", lambda path: False)
    listed = cli(home, "artifacts", "list", "--json")
    assert listed.exit_code == 0, listed.output
    assert {r["name"] for r in json.loads(listed.output)} == {"pt", "ft", "late"}  # caught up, privately
    lineage = cli(home, "lineage", child)
    assert lineage.exit_code == 0 and "(init) checkpoint pt" in lineage.output
    sql = cli(home, "sql", "SELECT count(*) AS n FROM edges", "--json")
    assert sql.exit_code == 0 and json.loads(sql.output) == [{"n": 2}]
    assert cli(home, "scores", pt).exit_code == 0
    assert _tree(home) == before
