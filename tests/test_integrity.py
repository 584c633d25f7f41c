"""Nothing wrong is ever recorded under a trusted id.

- Bytes that changed while size and mtime stayed (bit rot, `cp -a`, rsync, a restore) are refused by
  every read that feeds a registered computation (`Workspace.path`: vector stats, merge, evaluate) and
  by every registration that names them as a parent; nothing new is registered.
- A sidecar carries a seal over its metadata (kind, name, config, parents, files, provenance); an
  edited one is refused when read, so a rebuild cannot propagate forged lineage.
- `capvector verify [ID…|--all]` re-hashes the store and names each bad id (exit 1), 0 on a clean one.
"""

import json
import os
import time
import uuid

import pytest
import torch
from conftest import run_cli
from safetensors.torch import load_file, save_file
from typer.testing import CliRunner

from capvector.artifacts import store as store_mod
from capvector.artifacts.api import ArtifactsAPI
from capvector.artifacts.errors import CorruptArtifact
from capvector.artifacts.records import SEAL_FIELD, metadata_digest
from capvector.artifacts.store import ArtifactStore
from capvector.flows.cli.main import app
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.steps import evaluation
from capvector.tasks.vector_commands import merge_cli, stats_cli

TINY = dict(d_model=32, n_layers=2, n_heads=4, chunk_size=4, vocab_size=64, max_instruction_tokens=6)
SHAPES = {"blocks.0.attn.weight": (6, 4), "blocks.0.attn.bias": (6,), "blocks.1.mlp.weight": (3, 6)}


def rot(path, offset: int = -1) -> None:
    """Flip bits of one byte in place and put the old times back: what bit rot or a restore leaves.

    The default offset is the last byte of the file: the high byte of a little-endian float32 of the
    last tensor, so a weight of ~0.01 becomes ~1e36 (the ‖γ‖ = 2.1e36 of the issue)."""
    st = os.stat(path)
    with open(path, "r+b") as f:
        f.seek(offset, os.SEEK_END if offset < 0 else os.SEEK_SET)
        byte = f.read(1)
        f.seek(-1, os.SEEK_CUR)
        f.write(bytes([byte[0] ^ 0x7F]))
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    after = os.stat(path)
    assert (after.st_size, after.st_mtime_ns) == (st.st_size, st.st_mtime_ns)


def edit_sidecar(store: ArtifactStore, artifact_id: str, change, reseal: bool = False) -> None:
    """Edit a sidecar as a person or a buggy tool would (optionally recomputing its seal)."""
    path = store.sidecar_path(artifact_id)
    doc = json.loads(open(path).read())
    change(doc)
    if reseal:
        doc[SEAL_FIELD] = metadata_digest(doc)
    open(path, "w").write(json.dumps(doc, indent=1))


def _checkpoint(tmp_path, name: str, seed: int, scale: float) -> str:
    gen = torch.Generator().manual_seed(seed)
    tensors = {k: scale * torch.randn(shape, generator=gen) for k, shape in SHAPES.items()}
    path = tmp_path / f"{name}.safetensors"
    save_file(tensors, str(path))
    return str(path)


@pytest.fixture
def ws(tmp_path):
    """A workspace with θ_pt (weights ~1) and a vector γ (~0.01), both registered."""
    workspace = Workspace(str(tmp_path / "home"))
    api = workspace.api
    pt = api.register_file(_checkpoint(tmp_path, "pt", 0, 1.0), kind="checkpoint", name="pt").id
    gamma = api.register_file(_checkpoint(tmp_path, "gamma", 1, 0.01), kind="vector", name="gamma").id
    return workspace, {"pt": pt, "gamma": gamma}


def _counts(workspace: Workspace) -> tuple[int, int]:
    """(artifacts in the store, rows in the catalogue)."""
    n_store = len(list(workspace.api.store.iter_ids()))
    n_catalogue = int(workspace.api.query("SELECT count(*) AS n FROM artifacts")["n"][0])
    return n_store, n_catalogue


# ---------------------------------------------------------------------------- 3: bit rot is refused
def test_rotted_checkpoint_is_refused_by_workspace_path(ws):
    workspace, ids = ws
    path = workspace.path(ids["pt"])
    rot(path)
    with pytest.raises(CorruptArtifact, match=ids["pt"]):
        workspace.path(ids["pt"])
    with pytest.raises(CorruptArtifact, match=ids["pt"]):
        Workspace(workspace.home).path(ids["pt"])  # another workspace (another step) too
    assert not workspace.artifact_is_intact(ids["pt"])
    assert workspace.path(ids["gamma"]).is_file()  # the intact one is still served


def test_rotted_member_of_a_directory_artifact_is_refused(tmp_path):
    workspace = Workspace(str(tmp_path / "home"))
    src = tmp_path / "sharded"
    src.mkdir()
    save_file({"a": torch.ones(8)}, str(src / "model-00001-of-00002.safetensors"))
    save_file({"b": torch.ones(8)}, str(src / "model-00002-of-00002.safetensors"))
    rec = workspace.api.register_dir(src, kind="checkpoint", name="sharded")
    rot(workspace.path(rec.id) / "model-00002-of-00002.safetensors")
    with pytest.raises(CorruptArtifact, match=rec.id):
        workspace.path(rec.id)


def test_a_file_planted_in_a_directory_artifact_is_refused(tmp_path):
    workspace = Workspace(str(tmp_path / "home"))
    src = tmp_path / "adapter"
    src.mkdir()
    (src / "adapter_config.json").write_text("{}")
    rec = workspace.api.register_dir(src, kind="adapter", name="a")
    (workspace.path(rec.id) / "extra.safetensors").write_bytes(b"not covered by the id")
    with pytest.raises(CorruptArtifact, match="extra.safetensors"):
        workspace.path(rec.id)


def test_vector_stats_of_a_rotted_vector_registers_nothing(ws):
    workspace, ids = ws
    gamma = workspace.path(ids["gamma"])
    assert max(float(t.abs().max()) for t in load_file(str(gamma)).values()) < 1.0
    rot(gamma)
    before = _counts(workspace)
    with pytest.raises(CorruptArtifact, match=ids["gamma"]):
        stats_cli(workspace, ids["gamma"], ids["pt"], None)
    assert _counts(workspace) == before


def test_merge_force_onto_a_rotted_base_registers_nothing(ws, tmp_path):
    workspace, ids = ws
    rot(workspace.path(ids["pt"]))
    before = _counts(workspace)
    out = tmp_path / "merged.safetensors"
    with pytest.raises(CorruptArtifact, match=ids["pt"]):
        merge_cli(workspace, ids["pt"], [(ids["gamma"], 1.1)], out, None, None, force=True)
    assert not out.exists() and _counts(workspace) == before


@pytest.mark.parametrize("which", ["pt", "gamma"])
def test_the_vector_steps_refuse_a_rotted_input_by_the_hashes_taken_while_reading_it(ws, which):
    """The merge and mean steps read each input once, hashing it (Workspace.stream), and register
    nothing when what was read is not the input's id; intact inputs give what `path` reads give."""
    from capvector.tasks.steps.vectors import run_mean_vector, run_merge

    workspace, ids = ws
    merged = run_merge(workspace, "θ_meta", {"base": ids["pt"], "vector": ids["gamma"]}, {"alpha": 1.1})
    record = workspace.api.get(merged)
    assert {p.id for p in workspace.api.ancestors(merged, max_depth=1)} >= {ids["pt"], ids["gamma"]}
    want = {k: v + 1.1 * load_file(str(workspace.path(ids["gamma"])))[k]
            for k, v in load_file(str(workspace.path(ids["pt"]))).items()}  # fmt: skip
    got = load_file(str(workspace.path(record.id)))
    assert all(torch.equal(got[k], want[k]) for k in want)
    rot(workspace.path(ids[which]))
    before = _counts(workspace)
    with pytest.raises(CorruptArtifact, match=ids[which]):
        run_merge(workspace, "θ_meta 2", {"base": ids["pt"], "vector": ids["gamma"]}, {"alpha": 0.5})
    with pytest.raises(CorruptArtifact, match=ids[which]):
        run_mean_vector(workspace, "γ̄", {"vector 0": ids["pt"], "vector 1": ids["gamma"]}, {})
    assert _counts(workspace) == before


def test_evaluate_of_a_rotted_checkpoint_registers_nothing(tmp_path, monkeypatch):
    from capvector.core.evaluation.rollouts import EvalConfig
    from capvector.core.policies import L1ChunkConfig, L1ChunkPolicy
    from capvector.core.policies.base import save_policy

    workspace = Workspace(str(tmp_path / "home"))
    torch.manual_seed(0)
    saved = save_policy(L1ChunkPolicy(L1ChunkConfig(**TINY)), tmp_path / "policy.safetensors")
    ckpt = workspace.api.register_file(saved, kind="checkpoint", name="policy").id
    rot(workspace.path(ckpt))
    import prefect.artifacts  # the step imports it when it has run: patched where it is read

    monkeypatch.setattr(prefect.artifacts, "create_table_artifact", lambda **_: None)  # no Prefect API needed
    config = EvalConfig(tasks=["reach-v3"], episodes_per_task=1, horizon=5, execute_steps=4).model_dump()
    before = _counts(workspace)
    with pytest.raises(CorruptArtifact, match=ckpt):
        evaluation.evaluate_checkpoint(workspace, "eval", ckpt, config)
    assert _counts(workspace) == before


def test_a_rotted_parent_cannot_be_named_by_a_registration(tmp_path):
    store = ArtifactStore(tmp_path / "store", cache_dir=tmp_path / "cache")
    parent = store.put_bytes(b"weights" * 100, "checkpoint", "p")
    rot(store.path(parent.id))
    with pytest.raises(CorruptArtifact, match=parent.id):
        store.put_bytes(b"scores", "evaluation", "e", parents=[(parent.id, "checkpoint")])
    assert list(store.iter_ids()) == [parent.id]


def test_verified_reads_hash_once_per_process_and_never_trust_a_changed_file(tmp_path, monkeypatch):
    store = ArtifactStore(tmp_path / "store", cache_dir=tmp_path / "cache")
    rec = store.put_bytes(b"w" * 4096, "checkpoint", "c")
    hashed = []
    real = store_mod.hash_stream

    def counting(f):
        hashed.append(1)
        return real(f)

    monkeypatch.setattr(store_mod, "hash_stream", counting)
    store.path(rec.id)
    store.path(rec.id)
    assert len(hashed) == 2  # written a moment ago: too fresh to remember (its times may still move)

    monkeypatch.setattr(store_mod, "RACY_WINDOW_NS", 0)
    hashed.clear()
    store.path(rec.id)
    ArtifactStore(tmp_path / "store", cache_dir=tmp_path / "cache").path(rec.id)  # another instance
    assert len(hashed) == 1  # remembered within this process
    time.sleep(0.05)  # past the filesystem clock's tick, so the change moves the ctime
    rot(store.path(rec.id, verify=False))
    with pytest.raises(CorruptArtifact, match=rec.id):
        store.path(rec.id)
    assert len(hashed) == 2

    store_mod.clear_verified_memo()
    monkeypatch.setattr(store_mod, "VERIFIED_TTL_NS", 0)
    rec2 = store.put_bytes(b"v" * 4096, "checkpoint", "d")
    hashed.clear()
    store.path(rec2.id)
    store.path(rec2.id)
    assert len(hashed) == 2  # an expired memo is not trusted


# ---------------------------------------------------------------------------- 4: metadata is sealed
def _lineage(tmp_path):
    api = ArtifactsAPI(str(tmp_path / "home"))
    a = api.store.put_bytes(b"a", "checkpoint", "a")
    b = api.store.put_bytes(b"b", "checkpoint", "b")
    api.sync()
    child = api.register_json({"x": 1}, "evaluation-ish", "child", {"lr": 1e-3}, parents=[(a.id, "base")])
    return api, a.id, b.id, child.id


EDITS = {
    "parents": lambda other: lambda d: d["parents"][0].update(id=other),
    "role": lambda other: lambda d: d["parents"][0].update(role="vector"),
    "drop parent": lambda other: lambda d: d.update(parents=[]),
    "name": lambda other: lambda d: d.update(name="renamed"),
    "config": lambda other: lambda d: d["config"].update(lr=1.0),
    "kind": lambda other: lambda d: d.update(kind="checkpoint"),
    "code version": lambda other: lambda d: d.update(code_version="git:forged"),
    "stripped seal": lambda other: lambda d: d.pop(SEAL_FIELD),
}


@pytest.mark.parametrize("edit", list(EDITS))
def test_edited_sidecar_is_refused_naming_the_id(tmp_path, edit):
    api, _, b, child = _lineage(tmp_path)
    edit_sidecar(api.store, child, EDITS[edit](b))
    with pytest.raises(CorruptArtifact, match=child) as err:
        api.get(child)
    assert "seal" in str(err.value)
    with pytest.raises(CorruptArtifact, match=child):
        Workspace(api.home).path(child)
    with pytest.raises(CorruptArtifact, match=child):
        api.store.put_bytes(b"grandchild", "report", "g", parents=[(child, "of")])


def test_rebuild_does_not_propagate_a_forged_lineage(tmp_path):
    api, a, b, child = _lineage(tmp_path)
    edit_sidecar(api.store, child, EDITS["parents"](b))
    report = api.rebuild()
    assert report.corrupt == [child]
    edges = api.query("SELECT parent, child FROM edges").values.tolist()
    assert [b, child] not in edges


def test_mtime_bookkeeping_keeps_the_seal(tmp_path):
    store = ArtifactStore(tmp_path / "store", cache_dir=tmp_path / "cache")
    rec = store.put_bytes(b"c" * 100, "checkpoint", "c", {"lr": 0.1})
    os.utime(store.path(rec.id), ns=(1, 1))
    store.path(rec.id)  # re-hashed, intact: the new mtime is recorded in the sidecar
    again = store.get(rec.id)
    assert again.files[0].mtime_ns == 1 and again.sealed and again.config == {"lr": 0.1}


def test_old_sidecars_without_a_seal_still_load(tmp_path):
    store = ArtifactStore(tmp_path / "store", cache_dir=tmp_path / "cache")
    rec = store.put_bytes(b"old", "checkpoint", "old")
    assert store.get(rec.id).sealed

    def as_format_1(doc):
        doc["format"] = 1
        doc.pop(SEAL_FIELD)

    edit_sidecar(store, rec.id, as_format_1)
    old = store.get(rec.id)
    assert not old.sealed and old.name == "old"
    assert store.path(rec.id).read_bytes() == b"old"


def test_re_registering_the_content_replaces_a_tampered_sidecar(tmp_path):
    store = ArtifactStore(tmp_path / "store", cache_dir=tmp_path / "cache")
    parent = store.put_bytes(b"p", "dataset", "p")
    rec = store.put_bytes(b"c", "checkpoint", "c", parents=[(parent.id, "data")])
    edit_sidecar(store, rec.id, lambda d: d.update(parents=[]))
    with pytest.raises(CorruptArtifact):
        store.get(rec.id)
    again = store.put_bytes(b"c", "checkpoint", "c", parents=[(parent.id, "data")])  # a deliberate re-run
    assert again.id == rec.id and [p.id for p in store.get(rec.id).parents] == [parent.id]


def test_path_escape_is_refused_even_under_a_valid_seal(tmp_path):
    store = ArtifactStore(tmp_path / "store", cache_dir=tmp_path / "cache")
    rec = store.put_bytes(b"x", "report", "r")
    edit_sidecar(store, rec.id, lambda d: d["files"][0].update(path="../../../../etc/passwd"), reseal=True)
    with pytest.raises(CorruptArtifact, match=rec.id):
        store.path(rec.id)


# ---------------------------------------------------------------------------- capvector verify
def verify(home, *args):
    return CliRunner().invoke(app, ["--home", str(home), "verify", *args])


def test_verify_all_is_clean_then_names_each_bad_id(ws):
    workspace, ids = ws
    home = workspace.home
    report = workspace.api.register_json({"ok": True}, "report", "r", parents=[(ids["pt"], "of")]).id
    result = verify(home, "--all")
    assert result.exit_code == 0, result.output
    assert "3 artifacts" in result.output and "0 bad" in result.output

    rot(workspace.path(ids["gamma"]))
    edit_sidecar(workspace.api.store, report, lambda d: d.update(name="forged"))
    result = verify(home, "--all")
    assert result.exit_code == 1, result.output
    assert ids["gamma"] in result.output and report in result.output and "2 bad" in result.output
    assert ids["pt"] not in result.output  # only the bad ones are listed

    assert verify(home, ids["pt"][:12]).exit_code == 0  # one id, by prefix
    bad = verify(home, ids["pt"][:12], ids["gamma"][:12])
    assert bad.exit_code == 1 and ids["gamma"] in bad.output
    missing = verify(home, "0123456789ab")
    assert missing.exit_code == 1 and "0123456789ab" in missing.output

    as_json = verify(home, "--all", "--json")
    rows = {r["id"]: r for r in json.loads(as_json.stdout)}
    assert rows[ids["gamma"]]["status"] == "corrupt" and rows[report]["status"] == "corrupt"
    assert rows[ids["pt"]]["status"] == "ok"


def test_verify_needs_ids_or_all(ws):
    workspace, _ = ws
    result = verify(workspace.home)
    assert result.exit_code != 0


def test_verify_reports_unsealed_sidecars_and_strict_fails_on_them(ws):
    workspace, ids = ws

    def as_format_1(doc):
        doc["format"] = 1
        doc.pop(SEAL_FIELD)

    edit_sidecar(workspace.api.store, ids["pt"], as_format_1)
    # A sidecar from before sealing, in a catalogue that never saw it sealed (indexed afresh): an
    # unsealed sidecar the catalogue knew sealed is a downgrade, refused (test_nothing_lost.py).
    os.remove(os.path.join(workspace.home, "catalogue.duckdb"))
    ArtifactsAPI(workspace.home)
    result = verify(workspace.home, "--all")
    assert result.exit_code == 0, result.output
    assert "unsealed" in result.output and ids["pt"] in result.output
    assert verify(workspace.home, "--all", "--strict").exit_code == 1


def test_verify_compares_a_resealed_forgery_with_the_catalogue(ws):
    """A determined editor recomputes the seal: the store accepts it, the catalogue's copy disagrees."""
    workspace, ids = ws
    child = workspace.api.register_json({"x": 1}, "report", "child", parents=[(ids["pt"], "base")]).id
    edit_sidecar(workspace.api.store, child, lambda d: d["parents"][0].update(id=ids["gamma"]), reseal=True)
    assert workspace.api.get(child).parents[0].id == ids["gamma"]  # the seal alone cannot tell
    result = verify(workspace.home, "--all")
    assert result.exit_code == 1, result.output
    assert child in result.output and "catalogue" in result.output


def test_verify_exit_status_through_the_console_entry_point(ws):
    workspace, ids = ws
    clean = run_cli("verify", "--all", home=workspace.home, check=False)
    assert clean.returncode == 0, clean.stderr
    rot(workspace.path(ids["pt"]))
    bad = run_cli("verify", "--all", home=workspace.home, check=False)
    assert bad.returncode == 1 and ids["pt"] in bad.stdout, (bad.stdout, bad.stderr)
    home = workspace.home
    stats = run_cli("vector", "stats", ids["gamma"], "--base", ids["pt"][:12], home=home, check=False)
    assert stats.returncode == 2 and ids["pt"] in stats.stderr and "corrupt" in stats.stderr


def test_audit_of_a_remote_store_reads_the_remote_bytes(tmp_path):
    store = ArtifactStore(f"memory://capvector-integrity-{uuid.uuid4().hex}", cache_dir=tmp_path / "cache")
    rec = store.put_bytes(b"hello" * 100, "dataset", "d")
    store.path(rec.id)  # a verified copy in the local cache
    assert store.audit(rec.id).status == "ok"
    store.fs.pipe_file(f"{store.object_path(rec.id)}/data.bin", b"jello" + b"hello" * 99)  # same size
    verdict = store.audit(rec.id)
    assert verdict.status == "corrupt" and rec.id in verdict.detail
