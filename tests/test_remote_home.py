"""A home on an object store (S3, served by a local moto server) or a shared path given as a file:// URL.

Registration commits every object under its final key and writes the sidecar last: a reader never
sees an artifact without all its files, and a writer killed before its sidecar leaves nothing that
counts as an artifact. Ids are those a local home gives the same content; the catalogue (kept in the
local cache for a remote home) lists the lineage and is rebuilt from the store alone.
"""

import json
import os
import uuid
from pathlib import Path

import pytest

pytest.importorskip("moto.server")
pytest.importorskip("s3fs")
boto3 = pytest.importorskip("boto3")

from typer.testing import CliRunner  # noqa: E402

from capvector.artifacts import catalogue as catalogue_mod  # noqa: E402
from capvector.artifacts.api import ArtifactsAPI  # noqa: E402
from capvector.artifacts.store import ArtifactStore  # noqa: E402
from capvector.flows.cli.main import app  # noqa: E402

TABLES = ["artifacts", "edges", "vector_stats", "eval_episodes", "eval_tasks", "runs"]


@pytest.fixture(params=["s3", "file"])
def home(request, tmp_path, monkeypatch):
    """A fresh home: s3://<new bucket>/home, or file:///<tmp>/shared/home."""
    monkeypatch.setenv("CAPVECTOR_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(catalogue_mod, "SETTLE_NS", 0)
    if request.param == "file":
        return f"file://{tmp_path / 'shared' / 'home'}"
    request.getfixturevalue("s3_endpoint")
    bucket = f"capvector-{uuid.uuid4().hex[:12]}"
    boto3.client("s3").create_bucket(Bucket=bucket)
    return f"s3://{bucket}/home"


def tables(api: ArtifactsAPI) -> dict[str, list]:
    return {t: api.query(f"SELECT * FROM {t} ORDER BY ALL").astype(str).values.tolist() for t in TABLES}


def checkpoint_dir(root: Path) -> Path:
    """A sharded-checkpoint-like folder: an index, two shards and a config in a subfolder."""
    (root / "meta").mkdir(parents=True)
    (root / "model.safetensors.index.json").write_text('{"weight_map": {"a": "model-00001.safetensors"}}')
    (root / "model-00001.safetensors").write_bytes(os.urandom(4096))
    (root / "model-00002.safetensors").write_bytes(b"\0" * 70_000)
    (root / "meta" / "config.json").write_text('{"hidden": 8}')
    return root


def register_all(api: ArtifactsAPI, data: Path, ckpt: Path) -> dict[str, str]:
    ids = {"data": api.register_file(data, "dataset", "demos").id}
    ids["ckpt"] = api.register_dir(ckpt, "checkpoint", "theta_pt", parents=[(ids["data"], "data")]).id
    ids["eval"] = api.register_json({"success": [1, 0, 1]}, "metrics", "eval pt").id
    ids["report"] = api.register_json(
        {"note": "ok"}, "report", "r", parents=[(ids["ckpt"], "checkpoint"), (ids["eval"], "evaluation")]
    ).id
    return ids


def test_register_read_list_rebuild(home, tmp_path):
    data = tmp_path / "demos.bin"
    data.write_bytes(os.urandom(10_000))
    ckpt = checkpoint_dir(tmp_path / "ckpt")
    api = ArtifactsAPI(home)
    assert not api.store.local or home.startswith("file://")
    ids = register_all(api, data, ckpt)
    # the same content in a plain local home gets the same ids
    assert register_all(ArtifactsAPI(tmp_path / "local_home"), data, ckpt) == ids

    store = api.store
    assert sorted(store.iter_ids()) == sorted(ids.values())
    assert store.path(ids["data"]).read_bytes() == data.read_bytes()
    local_ckpt = store.path(ids["ckpt"])
    for f in ckpt.rglob("*"):
        if f.is_file():
            assert (local_ckpt / f.relative_to(ckpt)).read_bytes() == f.read_bytes()
    assert store.read_bytes(ids["ckpt"], member="meta/config.json") == b'{"hidden": 8}'
    assert store.open_json(ids["eval"]) == {"success": [1, 0, 1]}
    assert all(store.audit(i).status == "ok" for i in ids.values())
    if not store.local:  # nothing left in staging, nothing but objects and sidecars
        assert store.fs.find(store._p("tmp")) == []

    # the catalogue lists them with their lineage
    fresh = ArtifactsAPI(home)
    rows = fresh.query("SELECT id, kind, name FROM artifacts ORDER BY name")
    assert sorted(rows["id"]) == sorted(ids.values())
    lineage = {(n.id, tuple(n.roles)) for n in fresh.ancestors(ids["report"])}
    assert lineage == {
        (ids["ckpt"], ("checkpoint",)),
        (ids["eval"], ("evaluation",)),
        (ids["data"], ("checkpoint", "data")),  # the roles along the path
    }

    # `capvector catalogue rebuild` from the store alone gives the same rows
    before = tables(fresh)
    runner = CliRunner()
    result = runner.invoke(app, ["--home", home, "catalogue", "rebuild", "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.stdout)
    assert report["artifacts"] == len(ids) and report["corrupt"] == []
    assert tables(ArtifactsAPI(home)) == before


def test_killed_before_sidecar_leaves_no_artifact(home, tmp_path, monkeypatch):
    api = ArtifactsAPI(home)
    store = api.store
    base = api.register_json({"base": 1}, "dataset", "base").id
    ckpt = checkpoint_dir(tmp_path / "ckpt")
    real_write_small = ArtifactStore._write_small

    def killed(self, dst, data):
        if dst.startswith(self._p("objects")):
            raise KeyboardInterrupt("killed between the objects and the sidecar")
        return real_write_small(self, dst, data)

    monkeypatch.setattr(ArtifactStore, "_write_small", killed)
    with pytest.raises(KeyboardInterrupt):
        api.register_dir(ckpt, "checkpoint", "theta", parents=[(base, "data")])
    with pytest.raises(KeyboardInterrupt):
        api.register_json({"late": 1}, "report", "late")
    monkeypatch.setattr(ArtifactStore, "_write_small", real_write_small)

    # the objects were written under their final keys; no reader counts them as artifacts
    fresh = ArtifactStore(store.url, cache_dir=tmp_path / "cache2")
    objects = store._p("objects") + "/"
    keys = [p[len(objects) :].split("/") for p in store.fs.find(store._p("objects"))]
    written = {k[1] for k in keys if len(k) > 2}  # objects/<shard>/<id>/<member...>
    assert len(written - {base}) == 2  # the checkpoint's files and the late report's are there
    assert list(fresh.iter_ids()) == [base]
    assert ArtifactsAPI(home).query("SELECT id FROM artifacts")["id"].tolist() == [base]
    result = CliRunner().invoke(app, ["--home", home, "catalogue", "rebuild", "--json"])
    assert result.exit_code == 0 and json.loads(result.stdout)["artifacts"] == 1

    # registering the same content again commits it over the leftovers
    again = api.register_dir(ckpt, "checkpoint", "theta", parents=[(base, "data")])
    assert store.audit(again.id).status == "ok"
    assert (store.path(again.id) / "meta" / "config.json").read_text() == '{"hidden": 8}'
    # gc leaves a young leftover alone (an object store's prefix is as old as its newest key: it may
    # be a write in progress), moves an old one aside (never deletes it); the artifacts stay
    young = store.gc()
    assert (young.removed, young.quarantined) == ([], [])
    gc = store.gc(older_than_s=0)
    assert len(gc.quarantined) == 1 and gc.quarantined[0].rsplit("/", 1)[-1] not in (base, again.id)
    assert sorted(store.iter_ids()) == sorted([base, again.id])
    assert store.fs.find(gc.quarantined[0])  # the bytes are still there, under quarantine/


def test_cli_import_then_list(home, tmp_path):
    import numpy as np
    from safetensors.numpy import save_file

    path = tmp_path / "theta.safetensors"
    save_file({"w": np.arange(12, dtype=np.float32).reshape(3, 4)}, str(path))
    runner = CliRunner()
    result = runner.invoke(app, ["import", str(path), "--home", home, "--name", "theta_ext"])
    assert result.exit_code == 0, (result.output, result.exception)
    artifact_id = result.stdout.strip().splitlines()[-1]
    listed = runner.invoke(app, ["artifacts", "list", "--home", home, "--json"])
    assert listed.exit_code == 0, listed.output
    assert [(r["id"], r["name"]) for r in json.loads(listed.stdout)] == [(artifact_id, "theta_ext")]
    assert ArtifactStore(f"{home}/store").path(artifact_id).read_bytes() == path.read_bytes()


def test_a_driver_sees_what_a_worker_committed_at_its_next_open_and_lists_only_after_a_change(
    s3_endpoint, tmp_path, monkeypatch
):
    """Each machine keeps its own catalogue of a remote home. A worker's commits rewrite the store's
    change token, so the driver's next open indexes them at once (before: up to 60 s of `0 rows`), and
    an open after no commit reads the token alone: no listing."""
    bucket = f"capvector-{uuid.uuid4().hex[:12]}"
    boto3.client("s3").create_bucket(Bucket=bucket)
    home = f"s3://{bucket}/home"
    monkeypatch.setenv("CAPVECTOR_CACHE", str(tmp_path / "driver-cache"))
    driver = ArtifactsAPI(home)
    base = driver.register_json({"base": 1}, "dataset", "base").id

    monkeypatch.setenv("CAPVECTOR_CACHE", str(tmp_path / "worker-cache"))  # another machine
    worker = ArtifactsAPI(home)
    made = [
        worker.register_json({"i": i}, "metrics", f"eval {i}", parents=[(base, "data")]).id for i in range(3)
    ]

    monkeypatch.setenv("CAPVECTOR_CACHE", str(tmp_path / "driver-cache"))
    listings = []
    real_iter_ids = ArtifactStore.iter_ids
    monkeypatch.setattr(ArtifactStore, "iter_ids", lambda self: listings.append(1) or real_iter_ids(self))
    again = ArtifactsAPI(home)
    assert sorted(again.query("SELECT id FROM artifacts")["id"]) == sorted([base, *made])
    assert {n.id for n in again.descendants(base)} == set(made)
    assert len(listings) == 1
    ArtifactsAPI(home)  # nothing committed since: the token alone answers
    assert len(listings) == 1


def test_a_fresh_machine_finds_a_step_another_machine_computed(s3_endpoint, tmp_path, monkeypatch):
    """The step cache's index lives beside each machine's catalogue; the artifacts record their cache
    key in the store. A driver on another machine (its own CAPVECTOR_CACHE, no index entry), whose
    catalogue was opened just before the worker computed the step, gets the artifact from the cache at
    its next open instead of computing the step again (before the change token: recomputed for 60 s)."""
    from capvector.tasks.runtime.caching import cached_step
    from capvector.tasks.runtime.workspace import Workspace

    bucket = f"capvector-{uuid.uuid4().hex[:12]}"
    boto3.client("s3").create_bucket(Bucket=bucket)
    home = f"s3://{bucket}/home"
    computed = []

    def produce(key: str, workspace: Workspace) -> str:
        computed.append(key)
        return workspace.api.register_json({"n": 1}, "metrics", "step", config={"cache_key": key}).id

    def run_step(cache: str) -> str:
        monkeypatch.setenv("CAPVECTOR_CACHE", str(tmp_path / cache))
        workspace = Workspace(home)
        return cached_step(workspace, "metrics", {}, {"n": 1}, lambda key: produce(key, workspace))

    monkeypatch.setenv("CAPVECTOR_CACHE", str(tmp_path / "driver"))
    Workspace(home)  # the driver starts: its catalogue is caught up with an empty store
    first = run_step("worker")
    assert run_step("driver") == first
    assert len(computed) == 1


COMMIT_ELSEWHERE = """
import sys
from capvector.artifacts.store import ArtifactStore
print(ArtifactStore(sys.argv[1]).put_json({"from": "another process"}, "metrics", "other").id)
"""


def test_a_store_sees_what_another_process_committed_after_it_listed(home, tmp_path):
    """s3fs caches directory listings and never refreshes them: a store that had listed a shard (or
    looked for a sidecar there) did not see a sidecar another process wrote into it afterwards, and a
    study on an S3 home failed with `no artifact …` for an artifact that was in the bucket."""
    import hashlib
    import subprocess
    import sys

    url = f"{home}/store"
    store = ArtifactStore(url)
    doc = json.dumps({"from": "another process"}, sort_keys=True, indent=1, ensure_ascii=False).encode()
    expected = hashlib.sha256(doc).hexdigest()  # a one-file artifact's id is its sha256
    # this process looks first, at a shard that holds something else (a killed write's leftover)
    store.put_json({"here": 1}, "metrics", "mine")
    store.fs.makedirs(store._p("objects", expected[:2], "leftover"), exist_ok=True)
    store.fs.pipe_file(store._p("objects", expected[:2], "leftover", "data.bin"), b"x")
    store.fs.find(store._p("objects"))
    assert not store.exists(expected) and not store.exists(expected[:8])

    made = subprocess.run(
        [sys.executable, "-c", COMMIT_ELSEWHERE, url],
        capture_output=True,
        text=True,
        check=True,
        cwd=Path(__file__).resolve().parent.parent,
    ).stdout.strip()
    assert made == expected
    assert store.exists(expected) and store.exists(expected[:8])
    assert store.resolve(expected[:8]) == expected
    assert store.open_json(expected) == {"from": "another process"}
    assert expected in set(store.iter_ids())
    assert ArtifactStore(url).get(expected).name == "other"  # a new store in this process too
