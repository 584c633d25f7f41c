"""The step cache is checked, shared and healed (issue 25, items 3, 4, 5).

- A hit must be the artifact its key produced: an index entry naming an artifact recorded under another
  cache key (two entries swapped, an id edited) is a miss, recomputed with one warning line naming the
  step, and `capvector verify --all` lists it; the same bytes produced under two keys stay a hit.
- Two processes computing one step at once: the second waits on the key's lock (an flock under
  `<home>/locks/`) and reuses the first's artifact; a lock whose holder was killed -9 blocks nothing.
- A cached train step whose snapshot artifacts were deleted from the store is a miss and is rerun.
- A remote home's index objects in the store (`index/<key[:2]>/<key>.json`) are checked by `verify --all`
  too: a forged, dangling or garbled one fails it naming its key, and nothing is removed or rewritten.
"""

import json
import os
import re
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest
from typer.testing import CliRunner

from capvector.artifacts.store import ArtifactStore
from capvector.flows.cli.main import app
from capvector.tasks.runtime.caching import cached_step, lookup
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.steps.training import run_train
from tests.test_trainer import TINY, make_dataset, quick

REPO = Path(__file__).resolve().parents[1]


def verify_all(home) -> tuple[int, str]:
    result = CliRunner().invoke(app, ["--home", str(home), "verify", "--all"])
    return result.exit_code, result.output


def entry_of(workspace: Workspace, artifact_id: str) -> Path:
    (path,) = [p for p in workspace.cache_dir.glob("*.json") if artifact_id in p.read_text()]
    return path


@pytest.fixture
def trained(tmp_path):
    """A home with a dataset and two train steps from scratch, at lr 0.001 and lr 0.003."""
    workspace = Workspace(str(tmp_path / "home"))
    data = workspace.api.register_dir(make_dataset().save(tmp_path / "data"), kind="dataset", name="d").id
    configs = {
        lr: {
            "policy": {"type": "l1_chunk", **TINY},
            "train": quick(steps=8, warmup_steps=2, lr=lr, checkpoint_every=4, snapshot_steps=[4]).model_dump(
                mode="json"
            ),
        }
        for lr in (0.001, 0.003)
    }
    ids = {lr: run_train(workspace, f"sft lr {lr}", {"data": data}, cfg) for lr, cfg in configs.items()}
    return workspace, {"data": data}, configs, ids


# ---------------------------------------------------------------------------- 3: hits are checked
def test_swapped_cache_entries_are_refused_recomputed_and_reported(trained, capfd):
    workspace, inputs, configs, ids = trained
    low, high = entry_of(workspace, ids[0.001]), entry_of(workspace, ids[0.003])
    a, b = low.read_text(), high.read_text()
    low.write_text(b)
    high.write_text(a)

    code, output = verify_all(workspace.home)
    assert code == 1, output
    assert f"step-cache/{low.stem}" in output and f"step-cache/{high.stem}" in output
    capfd.readouterr()

    again = {lr: run_train(workspace, f"sft lr {lr}", inputs, cfg) for lr, cfg in configs.items()}
    assert again == ids  # recomputed (training is deterministic), never the other lr's checkpoint
    for lr, artifact_id in again.items():
        assert workspace.api.get(artifact_id).config["train_step"]["train"]["lr"] == lr
    warnings = [line for line in capfd.readouterr().err.splitlines() if "warning" in line]
    assert len(warnings) == 2, warnings
    assert "'sft lr 0.001'" in warnings[0] and "recomputing" in warnings[0]
    assert "'sft lr 0.003'" in warnings[1]
    code, output = verify_all(workspace.home)
    assert code == 0, output


def _producer(workspace, calls, tmp_path, payload=None):
    def produce(key):
        calls.append(key)
        src = tmp_path / f"payload-{len(calls)}.json"
        src.write_text(json.dumps(payload if payload is not None else {"key": key}))
        return workspace.api.register_file(src, kind="report", name="x", config={"cache_key": key}).id

    return produce


def test_an_entry_whose_id_was_edited_is_a_miss(tmp_path):
    """Entries as older versions wrote them ({"artifact_id"} alone), their ids exchanged."""
    workspace = Workspace(str(tmp_path / "home"))
    calls: list[str] = []
    produce = _producer(workspace, calls, tmp_path)
    first = cached_step(workspace, "report", {}, {"a": 1}, produce)
    second = cached_step(workspace, "report", {}, {"a": 2}, produce)
    key1, key2 = calls
    for key, artifact_id in ((key1, second), (key2, first)):
        (workspace.cache_dir / f"{key}.json").write_text(json.dumps({"artifact_id": artifact_id}))
    assert lookup(workspace, key1) is None and lookup(workspace, key2) is None
    assert cached_step(workspace, "report", {}, {"a": 1}, produce) == first
    assert cached_step(workspace, "report", {}, {"a": 2}, produce) == second
    assert len(calls) == 4


def test_the_same_bytes_under_two_keys_stay_a_hit(tmp_path):
    """Content addressing keeps the first record of equal bytes (e.g. a step rerun after a code change):
    the second key's entry still answers, without recomputing on every run, and verify is clean."""
    workspace = Workspace(str(tmp_path / "home"))
    calls: list[str] = []
    produce = _producer(workspace, calls, tmp_path, payload={"same": True})
    first = cached_step(workspace, "report", {}, {"a": 1}, produce)
    assert cached_step(workspace, "report", {}, {"a": 2}, produce) == first
    assert workspace.api.get(first).config["cache_key"] == calls[0]
    assert cached_step(workspace, "report", {}, {"a": 2}, produce) == first
    assert cached_step(workspace, "report", {}, {"a": 1}, produce) == first
    assert len(calls) == 2
    code, output = verify_all(workspace.home)
    assert code == 0, output


# ---------------------------------------------------------------------------- 4: one computation per key
def _slow_step(home, log, hold, stderr=subprocess.PIPE) -> subprocess.Popen:
    """tests/slow_step.py in a process of its own; `hold`: seconds, or `until=PATH` (see there)."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    env.pop("CAPVECTOR_QUIET", None)
    return subprocess.Popen(
        [sys.executable, "-c", "from tests.slow_step import main; main()", str(home), str(log), str(hold)],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=stderr,
        text=True,
    )


def _wait_for_lines(path: Path, n: int, timeout: float = 120) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline:
        if path.exists() and len(path.read_text().splitlines()) >= n:
            return
        time.sleep(0.05)
    raise AssertionError(f"{path} never got {n} line(s)")


def test_two_processes_running_one_step_compute_it_once(tmp_path):
    """The first holds the key's lock until the second says it waits for it (not for a fixed time: a
    second process that takes longer to start on a loaded machine would find the step done)."""
    home, log = tmp_path / "home", tmp_path / "computations"
    release, err_path = tmp_path / "release", tmp_path / "second.err"
    first = _slow_step(home, log, f"until={release}")
    _wait_for_lines(log, 1)  # the first is computing, under the key's lock
    with err_path.open("w") as err_file:
        second = _slow_step(home, log, 0, stderr=err_file)
    try:
        deadline = time.monotonic() + 120
        while "[slow step] waiting for another run" not in err_path.read_text():
            assert second.poll() is None and time.monotonic() < deadline, err_path.read_text()
            time.sleep(0.05)
    finally:
        release.touch()
    out1, err1 = first.communicate(timeout=300)
    out2, _ = second.communicate(timeout=300)
    assert first.returncode == 0 and second.returncode == 0, (err1, err_path.read_text())
    assert out1.strip() == out2.strip() and len(out1.strip()) == 64
    assert len(log.read_text().splitlines()) == 1, "the step was computed twice"
    assert list((home / "locks").glob("*.lock"))


def test_a_lock_whose_holder_was_killed_blocks_nothing(tmp_path):
    home, log = tmp_path / "home", tmp_path / "computations"
    holder = _slow_step(home, log, 600)
    _wait_for_lines(log, 1)
    holder.send_signal(signal.SIGKILL)
    holder.communicate()
    started = time.monotonic()
    nxt = _slow_step(home, log, 0)
    out, err = nxt.communicate(timeout=120)
    assert nxt.returncode == 0, err
    assert len(log.read_text().splitlines()) == 2  # the killed computation did not commit; this one did
    assert "waiting" not in err and time.monotonic() - started < 100
    assert Workspace(str(home)).api.get(out.strip()).kind == "report"


# ---------------------------------------------------------------------------- 5: lost snapshots are rerun
def test_a_train_step_whose_snapshot_left_the_store_is_rerun(trained, capfd):
    workspace, inputs, configs, ids = trained
    record = workspace.api.get(ids[0.001])
    snapshot = record.config["snapshots"]["4"]
    store = workspace.api.store
    import shutil

    shutil.rmtree(store.object_path(snapshot))
    os.remove(store.sidecar_path(snapshot))
    assert not workspace.artifact_is_intact(snapshot)
    capfd.readouterr()

    assert run_train(workspace, "sft lr 0.001", inputs, configs[0.001]) == ids[0.001]
    assert workspace.artifact_is_intact(snapshot)  # trained again: the same bytes, the same id
    err = capfd.readouterr().err
    assert "'sft lr 0.001'" in err and "snapshot" in err
    assert run_train(workspace, "sft lr 0.003", inputs, configs[0.003]) == ids[0.003]  # untouched: a hit
    assert "warning" not in capfd.readouterr().err


# ---------------------------------------------------------------------------- the store's index objects
@pytest.fixture
def remote_trained(tmp_path, monkeypatch):
    """A remote home (memory://: its step-cache entries are also index objects in the store) after one
    train step with a snapshot: (workspace, that step's cache key, its artifact id)."""
    monkeypatch.setenv("CAPVECTOR_CACHE", str(tmp_path / "cache"))
    workspace = Workspace(f"memory://capvector-trust-{uuid.uuid4().hex}")
    data = workspace.api.register_dir(make_dataset().save(tmp_path / "data"), kind="dataset", name="d").id
    train = quick(steps=8, warmup_steps=2, checkpoint_every=4, snapshot_steps=[4]).model_dump(mode="json")
    cfg = {"policy": {"type": "l1_chunk", **TINY}, "train": train}
    artifact_id = run_train(workspace, "sft", {"data": data}, cfg)
    yield workspace, workspace.api.get(artifact_id).config["cache_key"], artifact_id
    store = workspace.api.store
    store.fs.rm(store.root, recursive=True)


def test_verify_all_checks_index_objects_and_hashes_each_artifact_once(remote_trained, monkeypatch):
    workspace, key, _ = remote_trained
    store = workspace.api.store
    assert key in store.iter_index_keys()
    hashed: list[str] = []
    real = ArtifactStore._verify

    def counting(self, record, *args, **kwargs):
        hashed.append(record.id)
        return real(self, record, *args, **kwargs)

    monkeypatch.setattr(ArtifactStore, "_verify", counting)
    code, output = verify_all(workspace.home)
    assert code == 0, output
    counted = re.search(r"(\d+) index objects in the store: 0 bad", output)
    assert counted and int(counted.group(1)) >= 1, output
    assert sorted(hashed) == sorted(store.iter_ids())  # each artifact once: the index check hashed none


@pytest.mark.parametrize("case", ["forged", "missing-id", "garbage", "oversized"])
def test_verify_all_fails_on_a_bad_index_object_and_changes_nothing(remote_trained, case):
    workspace, key, artifact_id = remote_trained
    store = workspace.api.store
    other = workspace.api.get(artifact_id).parents[0].id  # a real artifact, recorded under no such key
    content = {
        "forged": json.dumps({"artifact_id": other, "cache_key": key, "recorded_under": key}).encode(),
        "missing-id": json.dumps({"artifact_id": "0" * 64, "cache_key": key, "recorded_under": key}).encode(),
        "garbage": b"\x00\xff not json {",
        "oversized": b"x" * 5000,
    }[case]
    store.put_index_entry(key, content)
    ids = sorted(store.iter_ids())

    code, output = verify_all(workspace.home)
    assert code == 1, output
    (line,) = [x for x in output.splitlines() if f"index/{key}" in x]
    status, why = {
        "forged": ("MISMATCH", other[:12]),
        "missing-id": ("MISSING", "0" * 64),
        "garbage": ("CORRUPT", "not an index entry"),
        "oversized": ("CORRUPT", "4096 bytes"),
    }[case]
    assert line.startswith(status) and why in line, line
    assert f"{len(ids)} artifacts" in output and "0 bad" in output  # the artifacts themselves are whole
    assert "1 bad" in output.splitlines()[-1]
    rows = json.loads(CliRunner().invoke(app, ["--home", workspace.home, "verify", "--all", "--json"]).stdout)
    assert [r["status"] for r in rows if r["id"] == f"index/{key}"] == [status.lower()]

    assert sorted(store.iter_ids()) == ids  # nothing removed
    assert all(store.audit(i).status == "ok" for i in ids)
    raw = store.fs.cat_file(store.index_entry_path(key))
    assert raw == content  # nor rewritten
