"""Real processes: two concurrent writers, a lock held too long, and a writer killed mid-artifact."""

import multiprocessing as mp
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from capvector.artifacts.api import ArtifactsAPI
from capvector.artifacts.catalogue import Catalogue
from capvector.artifacts.errors import CatalogueBusy
from capvector.artifacts.records import RunRecord

REPO = Path(__file__).resolve().parent.parent
N_EACH = 30


def register_many(home: str, worker: int, n: int) -> int:
    """Child process body: n registrations, each a separate store write and short catalogue transaction."""
    api = ArtifactsAPI(home)
    root = api.register_json({"worker": worker, "root": True}, "dataset", f"root-{worker}")
    for i in range(n - 1):
        api.register_json(
            {"worker": worker, "i": i}, "checkpoint", f"w{worker}-{i}", parents=[(root.id, "data")]
        )
    return api.catalogue.retries


def test_two_processes_register_concurrently(tmp_path):
    home = str(tmp_path / "home")
    ArtifactsAPI(home)  # create the catalogue before the race, as a flow process would
    ctx = mp.get_context("spawn")
    with ctx.Pool(2) as pool:
        retries = pool.starmap(register_many, [(home, 0, N_EACH), (home, 1, N_EACH)])
    api = ArtifactsAPI(home)
    assert api.query("SELECT count(*) n FROM artifacts")["n"][0] == 2 * N_EACH
    assert api.query("SELECT count(*) n FROM edges")["n"][0] == 2 * (N_EACH - 1)
    assert len(list(api.store.iter_ids())) == 2 * N_EACH
    root0 = api.query("SELECT id FROM artifacts WHERE name = 'root-0'")["id"][0]
    assert len(api.descendants(root0)) == N_EACH - 1
    print(f"lock retries per process: {retries}")


HOLD_LOCK = textwrap.dedent("""
    import sys, time, duckdb
    con = duckdb.connect(sys.argv[1])
    print("locked", flush=True)
    time.sleep(float(sys.argv[2]))
    con.close()
""")


def hold_lock(path: Path, seconds: float) -> subprocess.Popen:
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLD_LOCK, str(path), str(seconds)], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout.readline().strip() == "locked"
    return proc


def test_lock_held_briefly_is_waited_out_and_too_long_is_reported(tmp_path):
    path = tmp_path / "catalogue.duckdb"
    cat = Catalogue(path, max_wait_s=0.5)
    holder = hold_lock(path, 30)
    try:
        t0 = time.monotonic()
        with pytest.raises(CatalogueBusy, match="stayed locked"):
            cat.query("SELECT count(*) FROM artifacts")  # readers block on a writer's lock too
        assert time.monotonic() - t0 < 2.0  # bounded wait
    finally:
        holder.kill()
        holder.wait()
    patient = Catalogue(path, max_wait_s=20)
    holder = hold_lock(path, 0.4)
    patient.put_run(RunRecord(flow_run_id="r1", flow_name="f"))
    holder.wait()
    assert patient.retries > 0
    assert patient.query("SELECT flow_run_id FROM runs").values.tolist() == [["r1"]]


SLOW_WRITER = textwrap.dedent("""
    import sys
    from capvector.artifacts.api import ArtifactsAPI
    api = ArtifactsAPI(sys.argv[1])
    print("ready", flush=True)
    api.register_file(sys.argv[2], "checkpoint", "never finished", filename="model.safetensors")
    print("finished", flush=True)
""")


def test_writer_killed_mid_artifact_leaves_nothing_visible(tmp_path):
    """The source is a FIFO we feed slowly, so the kill lands while the artifact is half written."""
    home = tmp_path / "home"
    api = ArtifactsAPI(home)
    before = api.register_json({"x": 1}, "dataset", "already there")
    fifo = tmp_path / "slow.fifo"
    os.mkfifo(fifo)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    child = subprocess.Popen(
        [sys.executable, "-c", SLOW_WRITER, str(home), str(fifo)], stdout=subprocess.PIPE, text=True, env=env
    )
    assert child.stdout.readline().strip() == "ready"
    staging = Path(api.store.root) / "tmp"
    with open(fifo, "wb") as feed:
        for _ in range(8):
            feed.write(os.urandom(1 << 20))
            feed.flush()
        deadline = time.monotonic() + 10
        while not any(p.stat().st_size > 0 for p in staging.rglob("*") if p.is_file()):
            assert time.monotonic() < deadline, "child never started writing"
            time.sleep(0.01)
        child.send_signal(signal.SIGKILL)
        child.wait()
    assert child.returncode == -signal.SIGKILL
    assert list(api.store.iter_ids()) == [before.id]
    assert api.query("SELECT id FROM artifacts")["id"].tolist() == [before.id]
    assert api.rebuild().artifacts == 1
    leftovers = api.gc(older_than_s=0).store
    assert leftovers and all(p.startswith(str(staging)) for p in leftovers)
    assert not any(staging.iterdir())
    assert api.path(before.id).exists()
