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
