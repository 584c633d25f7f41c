"""Issue 25, "Nothing wrong trusted, nothing lost": what the store and the catalogue must refuse to
read, believe or delete. Real store, real DuckDB catalogue, real CLI (typer's runner on the same app,
or the console entry point in a subprocess where the exit status and stderr line matter)."""

import json
import os
import stat
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file
from typer.testing import CliRunner

from artifacts import store as store_mod
from artifacts.api import ArtifactsAPI
from flows.cli import app

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
    assert len(mermaid.output.splitlines()) == 2 and "pt\\n" in mermaid.output


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
