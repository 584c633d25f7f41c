"""The catalogue catches up with the store by itself, and `capvector catalogue sync|rebuild|verify|gc`.

The store is the truth: a writer killed between its sidecar (the commit point) and its catalogue row, a
registration that met a locked catalogue, or a deleted catalogue.duckdb must all be repaired by the next
open, without re-reading every sidecar when nothing changed.
"""

import json
import os
import shutil
import subprocess
import sys
import textwrap
import time
import uuid
from datetime import datetime, timedelta
from pathlib import Path

import pytest
from typer.testing import CliRunner

from capvector.artifacts import catalogue as catalogue_mod
from capvector.artifacts.api import ArtifactsAPI
from capvector.artifacts.records import RunRecord
from capvector.artifacts.store import ArtifactStore
from capvector.flows.cli.main import app

REPO = Path(__file__).resolve().parent.parent
TABLES = ["artifacts", "edges", "vector_stats", "eval_episodes", "eval_tasks", "runs"]


@pytest.fixture(autouse=True)
def settled_at_once(monkeypatch):
    """A store listing counts as settled as soon as it is taken (the real window guards coarse mtimes)."""
    monkeypatch.setattr(catalogue_mod, "SETTLE_NS", 0)


def build(home) -> tuple[ArtifactsAPI, dict[str, str]]:
    api = ArtifactsAPI(home)
    ids = {}
    ids["demos"] = api.register_json({"demos": 1}, "dataset", "D_ext").id
    ids["pt"] = api.register_json({"w": "pt"}, "checkpoint", "theta_pt", parents=[(ids["demos"], "data")]).id
    ids["ft"] = api.register_json({"w": "ft"}, "checkpoint", "theta_ft", parents=[(ids["pt"], "init")]).id
    ids["ao"] = api.register_json({"w": "ao"}, "checkpoint", "theta_ao", parents=[(ids["pt"], "init")]).id
    ids["gamma"] = api.register_json(
        {"w": "g"}, "vector", "gamma", parents=[(ids["ao"], "minuend"), (ids["ft"], "subtrahend")]
    ).id
    ids["eval"] = api.register_evaluation(
        {
            "checkpoint_id": ids["ao"],
            "fingerprint": "fp",
            "episodes": [{"task": "reach-v3", "seed": 0, "success": True, "steps": 3, "return": 1.0}],
        },
        "eval ao",
    ).id
    ids["stats"] = api.register_vector_stats(ids["gamma"], [{"tensor": "w", "numel": 4, "l2": 0.5}]).id
    started = datetime(2026, 1, 2, 3, 4, 5, 678901)
    api.record_run(
        RunRecord(
            flow_run_id="run-1",
            flow_name="pipeline",
            parameters={"alpha": 1.1, "preset": "smoke"},
            state="COMPLETED",
            started_at=started,
            ended_at=started + timedelta(seconds=1),
        )
    )
    return api, ids


def tables(api: ArtifactsAPI) -> dict[str, list]:
    return {t: api.query(f"SELECT * FROM {t} ORDER BY ALL").astype(str).values.tolist() for t in TABLES}


def cli(home, *args: str, code: int = 0):
    result = CliRunner().invoke(app, ["--home", str(home), *args])
    assert result.exit_code == code, (result.output, result.exception)
    return result


def count_sidecar_reads(monkeypatch) -> dict[str, int]:
    calls = {"sidecars": 0, "listings": 0}
    load, listing = ArtifactStore._load_sidecar, ArtifactStore.iter_ids

    def counted_load(self, artifact_id):
        calls["sidecars"] += 1
        return load(self, artifact_id)

    def counted_listing(self):
        calls["listings"] += 1
        return listing(self)

    monkeypatch.setattr(ArtifactStore, "_load_sidecar", counted_load)
    monkeypatch.setattr(ArtifactStore, "iter_ids", counted_listing)
    return calls


# ---------------------------------------------------------------------------- item 5: catching up
def test_sidecar_without_row_is_indexed_by_the_next_open(tmp_path):
    """kill -9 between sidecar and row: the store has the artifact, the catalogue does not."""
    home = tmp_path / "home"
    api, ids = build(home)
    late = api.store.put_json({"w": "meta"}, "checkpoint", "theta_meta", parents=[(ids["gamma"], "vector")])
    assert late.id not in api.query("SELECT id FROM artifacts")["id"].tolist()  # the writer died here

    fresh = ArtifactsAPI(home)
    assert late.id in fresh.query("SELECT id FROM artifacts")["id"].tolist()
    assert [(r.id, r.roles) for r in fresh.ancestors(late.id, max_depth=1)] == [(ids["gamma"], ["vector"])]
    listed = json.loads(cli(home, "artifacts", "list", "--json").stdout)
    assert late.id in {r["id"] for r in listed}
    lineage = json.loads(cli(home, "lineage", late.id[:12], "--format", "json").stdout)
    assert {r["id"] for r in lineage} >= {ids["gamma"], ids["ao"], ids["ft"], ids["pt"], ids["demos"]}


def test_deleted_catalogue_comes_back_on_any_call(tmp_path):
    home = tmp_path / "home"
    api, ids = build(home)
    before = tables(api)
    listed = cli(home, "artifacts", "list", "--json").stdout
    api.catalogue.path.unlink()
    assert tables(ArtifactsAPI(home)) == before  # the API's first open rebuilt it

    api.catalogue.path.unlink()
    assert cli(home, "artifacts", "list", "--json").stdout == listed  # so does any command
    assert tables(ArtifactsAPI(home)) == before


def test_a_run_record_missing_from_the_catalogue_is_caught_up(tmp_path):
    home = tmp_path / "home"
    api, _ = build(home)
    assert api.sync().runs == 0  # a run row equal to its record is left alone
    api.store.put_run(RunRecord(flow_run_id="run-2", flow_name="sweep", state="RUNNING"))
    api.store.put_run(RunRecord(flow_run_id="run-1", flow_name="pipeline", state="FAILED"))  # updated
    runs = ArtifactsAPI(home).query("SELECT flow_run_id, state FROM runs ORDER BY 1").values.tolist()
    assert runs == [["run-1", "FAILED"], ["run-2", "RUNNING"]]


def test_open_with_nothing_to_catch_up_reads_no_sidecar(tmp_path, monkeypatch):
    home = tmp_path / "home"
    build(home)
    ArtifactsAPI(home)  # settles the marker
    calls = count_sidecar_reads(monkeypatch)
    api = ArtifactsAPI(home)
    assert calls == {"sidecars": 0, "listings": 0}
    api.store.put_json({"late": 1}, "report", "late")  # a new sidecar changes the store's fingerprint
    calls.update(sidecars=0, listings=0)  # the writer's own look for a committed copy is not the open's
    ArtifactsAPI(home)
    assert calls == {"sidecars": 1, "listings": 1}  # one listing, and only the new sidecar is read
    ArtifactsAPI(home)
    assert calls == {"sidecars": 1, "listings": 1}


def test_an_unsettled_listing_is_checked_again(tmp_path, monkeypatch):
    """A listing taken while the store's directories were just modified is not trusted by the next open:
    a sidecar written in the same timestamp tick would leave the fingerprint unchanged."""
    home = tmp_path / "home"
    build(home)
    monkeypatch.setattr(catalogue_mod, "SETTLE_NS", 10**12)
    ArtifactsAPI(home)
    calls = count_sidecar_reads(monkeypatch)
    ArtifactsAPI(home)
    assert calls["listings"] == 1 and calls["sidecars"] == 0
    monkeypatch.setattr(catalogue_mod, "SETTLE_NS", 0)
    ArtifactsAPI(home)
    ArtifactsAPI(home)
    assert calls["listings"] == 2


def test_copied_home_is_checked_against_its_own_store(tmp_path, monkeypatch):
    home = tmp_path / "home"
    build(home)
    ArtifactsAPI(home)
    shutil.copytree(home, tmp_path / "copy")
    copy = ArtifactsAPI(tmp_path / "copy")
    late = copy.store.put_json({"late": 1}, "report", "late")
    assert late.id in ArtifactsAPI(tmp_path / "copy").query("SELECT id FROM artifacts")["id"].tolist()
    assert late.id not in ArtifactsAPI(home).query("SELECT id FROM artifacts")["id"].tolist()


def test_unreadable_sidecar_is_not_indexed_and_does_not_fail_the_open(tmp_path):
    home = tmp_path / "home"
    api, ids = build(home)
    bad = api.store.put_json({"bad": 1}, "report", "bad", parents=[(ids["pt"], "data")])
    Path(api.store.sidecar_path(bad.id)).write_text("{ not json")
    fresh = ArtifactsAPI(home)  # indexes nothing wrong, and opens all the same
    assert bad.id not in fresh.query("SELECT id FROM artifacts")["id"].tolist()
    assert fresh.query("SELECT count(*) n FROM edges WHERE child = ?", [bad.id])["n"][0] == 0
    result = cli(home, "catalogue", "sync", code=1)
    assert bad.id in result.stdout and "failed verification" in result.stdout
    assert bad.id in cli(home, "catalogue", "verify", code=1).stdout


def test_a_remote_store_is_listed_only_when_its_change_token_moved(tmp_path, monkeypatch):
    """A remote store has no directory times: every commit rewrites its change token, and an open's
    first catalogue read lists the store only when the token differs from the one its last listing
    saw (an open alone lists nothing: see test_remote_cache_index). A store no writer gave a token
    (an older version wrote it) is listed when the last listing is older than REMOTE_SYNC_INTERVAL_S."""
    monkeypatch.setenv("CAPVECTOR_CACHE", str(tmp_path / "cache"))
    home = f"memory://capvector-sync-{uuid.uuid4().hex}"
    api = ArtifactsAPI(home)
    first = api.register_json({"a": 1}, "dataset", "a")
    ArtifactsAPI(home).query("SELECT 1")  # the token moved since the first listing: listed once more
    calls = count_sidecar_reads(monkeypatch)
    ArtifactsAPI(home).query("SELECT 1")
    assert calls["listings"] == 0  # nothing committed since
    late = api.store.put_json({"b": 1}, "checkpoint", "b", parents=[(first.id, "data")])  # no row
    before = dict(calls)
    fresh = ArtifactsAPI(home)
    assert calls["listings"] == before["listings"]  # not before a read
    assert [(r.id, r.roles) for r in fresh.ancestors(late.id)] == [(first.id, ["data"])]
    # the new commit: one listing, and only its sidecar read
    assert (calls["listings"] - before["listings"], calls["sidecars"] - before["sidecars"]) == (1, 1)

    # a store without a token (its writers predate it): listed at most once per interval
    old_home = f"memory://capvector-sync-{uuid.uuid4().hex}"
    writer = ArtifactsAPI(old_home)
    base = writer.register_json({"a": 1}, "dataset", "a")
    writer.store.fs.rm(writer.store._p("changes"))
    monkeypatch.setenv("CAPVECTOR_CACHE", str(tmp_path / "reader-cache"))
    assert base.id in ArtifactsAPI(old_home).query("SELECT id FROM artifacts")["id"].tolist()
    later = writer.store.put_json({"d": 1}, "checkpoint", "d", parents=[(base.id, "data")])
    writer.store.fs.rm(writer.store._p("changes"))
    assert later.id not in ArtifactsAPI(old_home).query("SELECT id FROM artifacts")["id"].tolist()
    monkeypatch.setattr(catalogue_mod, "REMOTE_SYNC_INTERVAL_S", 0.0)
    assert later.id in ArtifactsAPI(old_home).query("SELECT id FROM artifacts")["id"].tolist()


# ---------------------------------------------------------------------------- the commands
def test_catalogue_commands(tmp_path):
    home = tmp_path / "home"
    api, ids = build(home)
    out = json.loads(cli(home, "catalogue", "verify", "--json").stdout)
    assert out["rows_without_objects"] == [] and out["objects_without_rows"] == []

    late = api.store.put_json({"late": 1}, "report", "late", parents=[(ids["eval"], "data")])
    result = cli(home, "catalogue", "verify", code=1)  # verify reports; it does not repair
    assert late.id in result.stdout and "without a catalogue row" in result.stdout
    synced = json.loads(cli(home, "catalogue", "sync", "--json").stdout)
    assert synced["artifacts"] == 1
    cli(home, "catalogue", "verify")

    # an artifact removed from the store behind the catalogue's back: a row without an object
    gone = api.store.put_json({"gone": 1}, "report", "gone", parents=[(ids["pt"], "data")])
    api.catalogue.add(gone)
    os.remove(api.store.sidecar_path(gone.id))
    staged = Path(api.store.root) / "tmp" / "leftover"
    staged.mkdir(parents=True)
    result = cli(home, "catalogue", "verify", code=1)
    assert gone.id in result.stdout and "without an object" in result.stdout
    removed = json.loads(cli(home, "catalogue", "gc", "--older-than", "0", "--json").stdout)
    assert removed["rows"] == [gone.id] and str(staged) in removed["store"]
    assert not staged.exists()
    assert ArtifactsAPI(home).query("SELECT count(*) n FROM edges WHERE child = ?", [gone.id])["n"][0] == 0
    cli(home, "catalogue", "verify")

    before = tables(ArtifactsAPI(home))
    rebuilt = json.loads(cli(home, "catalogue", "rebuild", "--json").stdout)
    assert rebuilt["artifacts"] == len(ids) + 1 and rebuilt["corrupt"] == []
    assert tables(ArtifactsAPI(home)) == before
    assert "rebuilt" in cli(home, "catalogue", "rebuild").stdout


def test_schema_error_names_the_real_command(tmp_path):
    from capvector.artifacts.errors import SchemaTooNew

    message = str(SchemaTooNew(9, 2, "x.duckdb"))
    assert "capvector catalogue rebuild" in message
    result = CliRunner().invoke(app, ["catalogue", "--help"])
    assert all(c in result.stdout for c in ("sync", "rebuild", "verify", "gc"))


# ---------------------------------------------------------------------------- item 6: readers vs writers
LONG_QUERY = textwrap.dedent("""
    import sys
    from capvector.artifacts.api import ArtifactsAPI
    api = ArtifactsAPI(sys.argv[1])
    print("querying", flush=True)
    api.query("SELECT count(*) FROM range(100000000000) t(x) WHERE x % 7 = 3")
""")

RAW_READER = textwrap.dedent("""
    import sys, duckdb
    con = duckdb.connect(sys.argv[1], read_only=True)  # a DuckDB shell left open, say
    print("locked", flush=True)
    sys.stdin.read()  # until the test closes our stdin
    con.close()
""")


def _child(*args: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.Popen(
        [sys.executable, "-c", *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env
    )


def _release(holder: subprocess.Popen) -> None:
    holder.stdin.close()
    assert holder.wait(timeout=30) == 0


def test_long_sql_query_does_not_block_registration(tmp_path):
    """`capvector sql` with a query of minutes: registrations go on at their usual speed."""
    home = tmp_path / "home"
    api, ids = build(home)
    reader = _child(LONG_QUERY, str(home))
    try:
        assert reader.stdout.readline().strip() == "querying"
        time.sleep(1.0)  # the query is running
        assert reader.poll() is None
        writer = ArtifactsAPI(home, max_wait_s=5)
        t0 = time.monotonic()
        rec = writer.register_json({"during": 1}, "report", "during a long read", parents=[(ids["pt"], "x")])
        took = time.monotonic() - t0
        assert writer.pending == 0  # the row landed now, not later
        assert rec.id in writer.query("SELECT id FROM artifacts")["id"].tolist()
        assert took < 3.0, took
        assert reader.poll() is None  # the reader is still at it
    finally:
        reader.kill()
        reader.wait()


def test_a_query_that_runs_long_moves_to_a_snapshot(tmp_path, monkeypatch):
    home = tmp_path / "home"
    api, ids = build(home)
    snapshots = []
    snapshot_read = catalogue_mod.Catalogue._snapshot_read

    def counted(self, fn):
        snapshots.append(1)
        return snapshot_read(self, fn)

    monkeypatch.setattr(catalogue_mod.Catalogue, "_snapshot_read", counted)
    assert api.query("SELECT count(*) n FROM artifacts")["n"][0] == len(ids) and snapshots == []
    monkeypatch.setattr(catalogue_mod, "DIRECT_READ_S", 0.05)
    slow = "SELECT count(*) n FROM range(300000000) t(x), (SELECT count(*) c FROM artifacts) WHERE x % 7 = 3"
    assert api.query(slow)["n"][0] == len(range(3, 300000000, 7)) and snapshots == [1]
    assert not list(api.catalogue.path.parent.glob(catalogue_mod.SNAPSHOT_PREFIX + "*"))


def test_registration_never_fails_on_a_locked_catalogue(tmp_path):
    """Whoever holds the lock (a DuckDB shell, a hung process), the sidecar commit is the truth: the
    registration returns, and the row is indexed once the lock is free."""
    home = tmp_path / "home"
    api, ids = build(home)
    writer = ArtifactsAPI(home, max_wait_s=0.5)
    holder = _child(RAW_READER, str(api.catalogue.path))
    try:
        assert holder.stdout.readline().strip() == "locked"
        rec = writer.register_json({"locked": 1}, "report", "while locked", parents=[(ids["pt"], "x")])
        run = RunRecord(flow_run_id="run-9", flow_name="pipeline")
        writer.record_run(run)
        assert writer.store.exists(rec.id) and writer.pending == 2
        again = writer.register_json({"locked": 2}, "report", "still locked")
        assert writer.pending == 3 and writer.store.exists(again.id)
    finally:
        _release(holder)
    found = ArtifactsAPI(home).query("SELECT id FROM artifacts")["id"].tolist()  # the next open
    assert rec.id in found and again.id in found
    assert rec.id in {r.id for r in writer.descendants(ids["pt"])}  # pending rows are flushed before reads
    assert writer.pending == 0


def test_open_does_not_need_the_write_lock(tmp_path):
    """Opening an up-to-date catalogue takes only a shared lock, so a long reader does not block it."""
    home = tmp_path / "home"
    api, _ = build(home)
    some = api.query("SELECT id FROM artifacts LIMIT 1")["id"][0]
    holder = _child(RAW_READER, str(api.catalogue.path))
    try:
        assert holder.stdout.readline().strip() == "locked"
        t0 = time.monotonic()
        ArtifactsAPI(home, max_wait_s=5).ancestors(some)
        assert time.monotonic() - t0 < 2.0
    finally:
        _release(holder)
