"""Two flows on one fresh home at once record exactly what a lone run records (issue 27, item 3).

Once, two `capvector study --preset study-smoke` on one fresh home shared a training work folder
(`Workspace.run_dir`, one per content key), and one of them registered θ_pt, a 30-step run, with the
loss-curve steps [10, 20] inside its sealed record; `verify` stayed clean. Every step that writes into
a work folder now computes and registers under `cached_step`'s flock per content key, and asks the
cache again once it holds it (capvector.tasks.runtime.caching.step_lock), so the second run waits and reuses.

Here two `capvector run --preset smoke --json` start together on one fresh home; what they record is
compared with what the session's lone smoke run recorded (conftest `fresh_smoke_home`, an unwritten
copy of its home). The run runs every kind of step that writes into the home's `work/` folder:
training (its `run_dir`), demos, vector extraction and merge, evaluation (temporary `scratch()`
folders), held-out losses, the null vector and the analysis (a run is the smallest study); a study's
selections register from memory under the same lock. Checked: both exit 0 and print the lone run's
ids; every sealed record in the shared home equals the lone home's record of the same id once
provenance (times, run ids, speeds, code revision) is set aside; each trained checkpoint's loss curve
has all its logged steps; each training step was trained by one process only; `capvector verify --all
--strict` is clean on both homes. With `step_lock` made a no-op this test fails (seen: a run failing
on the loss curve the other run's finished step had removed).

Why `run --preset smoke` and not `study --preset study-smoke`: measured on this project's busy 2-core
machine, two concurrent smoke runs take ~41 s (a lone one ~27 s) and this whole test 70-80 s, against
~105 s for two concurrent study-smoke runs plus ~73 s for the lone one. The two runs start on a
Prefect home no server has initialised yet: once, concurrent first starts of the run servers raced on
its migrations (a duplicate index or block type killed one run). The lone run is the session's shared
one, not a third run here: it was a reference only, computed the same way, and `make test` saves a cold
smoke run.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path
from typing import Any

from conftest import REPO, own_server_env, run_cli

from capvector.artifacts.api import ArtifactsAPI

# Fields of a record that say when, where, how fast or by which run, not what: left out of the comparison.
PROVENANCE = {"created_at", "flow_run_id", "task_run_id", "code_version", "metadata_sha256"}
PROVENANCE_CONFIG = {"time", "steps_per_s", "samples_per_s", "wall_time_s"}
TRAINING_STARTED = re.compile(r"^\S+ \[(?P<step>[^\]]+)\] \d+/\d+ steps, (started|resumed)")


def _start(home: Path, out: Any, err: Any) -> subprocess.Popen:
    """`capvector run --preset smoke --json` on `home`, in a session of its own (see conftest.run_cli)."""
    env = own_server_env({**os.environ, "CAPVECTOR_HOME": str(home), "CAPVECTOR_QUIET": "1"})
    return subprocess.Popen(
        [sys.executable, "-m", "capvector", "run", "--preset", "smoke", "--json"],
        cwd=REPO,
        env=env,
        stdout=out,
        stderr=err,
        start_new_session=True,
    )


def _run_together(homes: list[Path], timeout: float = 900) -> list[tuple[int, str, str]]:
    """Start one smoke run per entry of `homes` at once; (exit code, stdout, stderr) of each."""
    files = [(tempfile.TemporaryFile("w+"), tempfile.TemporaryFile("w+")) for _ in homes]
    procs = [_start(home, out, err) for home, (out, err) in zip(homes, files, strict=True)]
    results = []
    try:
        for proc, (out, err) in zip(procs, files, strict=True):
            code = proc.wait(timeout=timeout)
            out.seek(0)
            err.seek(0)
            results.append((code, out.read(), err.read()))
    finally:
        for proc in procs:
            try:
                os.killpg(proc.pid, signal.SIGKILL)  # leftovers of the run's session (its server)
            except ProcessLookupError:
                pass
        for out, err in files:
            out.close()
            err.close()
    return results


def _strip(value: Any, keys: set[str]) -> Any:
    if isinstance(value, dict):
        return {k: _strip(v, keys) for k, v in value.items() if k not in keys}
    if isinstance(value, list):
        return [_strip(v, keys) for v in value]
    return value


def _records(home: Path) -> dict[str, dict[str, Any]]:
    """Every sealed record of the home's store (read through the store, which checks each seal), without
    its provenance."""
    api = ArtifactsAPI(str(home), catch_up=False)
    records = {}
    for artifact_id in sorted(api.store.iter_ids()):
        record = api.store.get(artifact_id)
        assert record.sealed, f"{artifact_id} has an unsealed sidecar"
        doc = {k: v for k, v in record.model_dump(mode="json").items() if k not in PROVENANCE}
        doc["files"] = [{k: v for k, v in f.items() if k != "mtime_ns"} for f in doc["files"]]
        doc["config"] = _strip(doc["config"], PROVENANCE_CONFIG)
        records[artifact_id] = doc
    return records


def _expected_curve_steps(train: dict[str, Any]) -> list[int]:
    """The steps a complete loss curve logs: every `log_every` steps, and the last one."""
    steps, every = train["steps"], train["log_every"]
    return sorted(set(range(every, steps + 1, every)) | {steps})


def _trainings(home: Path) -> Counter:
    """How many times each training step started (or resumed), over every run log of the home."""
    found: Counter = Counter()
    for log in sorted((home / "logs").glob("*.log")):
        for line in log.read_text().splitlines():
            match = TRAINING_STARTED.match(line)
            if match:
                found[match["step"]] += 1
    return found


def test_two_runs_on_one_home_at_once_record_what_a_lone_run_records(fresh_smoke_home, tmp_path, monkeypatch):
    shared = tmp_path / "shared"
    lone, alone = fresh_smoke_home
    # A Prefect home no server has initialised: the two run servers' first starts must not race on
    # its migrations and block types (capvector.flows.runtime.prefect_server holds PREFECT_HOME's boot lock
    # until ready).
    monkeypatch.setenv("PREFECT_HOME", str(tmp_path / "prefect"))
    results = _run_together([shared, shared])
    for code, _, err in results:
        assert code == 0, f"a run failed ({code}):\n{err[-3000:]}"
    first, second = (json.loads(out) for _, out, _ in results)
    for ids in (first, second, alone):
        ids.pop("report_file")  # in its own home
    # the content cache makes the lone run's ids the expected ones, step by step
    assert first == second == alone

    shared_records, lone_records = _records(shared), _records(lone)
    assert sorted(shared_records) == sorted(lone_records)  # the same artifacts, none twice
    for artifact_id, record in shared_records.items():
        assert record == lone_records[artifact_id], f"{record['kind']} {record['name']!r} differs"

    checkpoints = [r for r in shared_records.values() if "curve" in r["config"]]
    assert len(checkpoints) == 6  # θ_pt, θ_ft, θ_ao and the three downstream arms
    for record in checkpoints:
        train = record["config"]["train_step"]["train"]
        steps = [row["step"] for row in record["config"]["curve"]]
        assert steps == _expected_curve_steps(train), f"{record['name']!r}: loss curve steps {steps}"
        assert record["config"]["summary"]["resumed_from_step"] == 0, record["name"]

    # each training step ran in one process: the other run waited for it, then reused its checkpoint
    trained = _trainings(shared)
    assert trained == _trainings(lone) and set(trained.values()) == {1}, trained
    assert len(trained) == len(checkpoints)

    for home in (shared, lone):
        verify = run_cli("verify", "--all", "--strict", home=home)
        assert " 0 bad" in verify.stdout, verify.stdout
