"""Issue 38, item 1: a study whose home is on S3 (a moto server), run on a Dask cluster and killed with
SIGKILL while its γ draws are half done, is finished by the same command through the default process
pool on this machine: nothing it left half-written counts as committed, no lock or stale listing stops
the resume, no step is done twice, the catalogue is in step with the store, and the report's numbers
are study-smoke's golden ones, as a clean local run gives them (tests/golden_report.py)."""

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
from conftest import REPO, run_cli
from golden_report import golden_differences

from capvector.artifacts.api import ArtifactsAPI
from capvector.tasks.steps.study_analysis import StudyReport

STUDY = ("study", "--preset", "study-smoke")
# The first γ of the study's two draws committed: the other draw is still training or extracting.
MID_DRAW = re.compile(r"\[study study-smoke \d+/\d+\] draw \d capability vector γ: done")
STEP_LINE = re.compile(r"\[study study-smoke \d+/\d+\] (.+): (done|cached|failed)$")
WARNING = re.compile(r"^\d\d:\d\d:\d\d warning: ", re.MULTILINE)  # capvector's own (progress.emit)


def _run_until(argv: list[str], env: dict[str, str], err: Path, marker: re.Pattern, timeout: float) -> str:
    """Start the CLI in a session of its own, and kill that whole session with SIGKILL the moment its
    stderr shows `marker`; what it printed up to then."""
    with err.open("wb") as sink:
        proc = subprocess.Popen(
            argv, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=sink, start_new_session=True
        )
    deadline = time.monotonic() + timeout
    try:
        while not marker.search(err.read_text(errors="replace")):
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"never saw {marker.pattern!r} (exit {proc.poll()}):\n{err.read_text()[-3000:]}")
            time.sleep(0.2)
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait(timeout=60)
    return err.read_text(errors="replace")


def _steps(stderr: str) -> dict[str, str]:
    """Step -> outcome, from a run's `[study study-smoke k/N] step: outcome` lines."""
    return {m.group(1): m.group(2) for line in stderr.splitlines() if (m := STEP_LINE.search(line.rstrip()))}


def _wait_idle(address: str, timeout: float = 900) -> None:
    """Until no worker runs a task: a killed driver's task goes on in its worker's thread (the
    scheduler has forgotten it) and may commit after the resume."""
    from distributed import Client

    deadline = time.monotonic() + timeout
    with Client(address, timeout=60) as client:
        while any(client.run(lambda dask_worker: dask_worker.state.executing_count).values()):
            assert time.monotonic() < deadline, "the cluster's workers never went idle"
            time.sleep(1)


@pytest.mark.slow
def test_a_study_killed_mid_draw_on_s3_resumes_in_a_process_pool(cluster, tmp_path, monkeypatch):
    import boto3

    address, _, _ = cluster
    bucket = f"capvector-{uuid.uuid4().hex[:12]}"
    boto3.client("s3").create_bucket(Bucket=bucket)
    home = f"s3://{bucket}/study"
    cache = {"CAPVECTOR_CACHE": str(tmp_path / "driver-cache")}  # this machine's: catalogue, locks, index
    env = {**os.environ, "CAPVECTOR_HOME": home, "CAPVECTOR_QUIET": "0", **cache}
    argv = [sys.executable, "-m", "capvector", *STUDY, "--runner", "dask", "--address", address]

    started = time.monotonic()
    killed = _steps(_run_until(argv, env, tmp_path / "killed.err", MID_DRAW, timeout=3600))
    killed_at = time.monotonic() - started
    gammas = [s for s in killed if s.endswith("capability vector γ") and s.startswith("draw")]
    assert len(gammas) == 1 and not any(o == "failed" for o in killed.values()), killed

    resumed = run_cli(*STUDY, "--json", home=home, env={**cache, "CAPVECTOR_QUIET": "0"}, timeout=3600)
    resumed_s = time.monotonic() - started - killed_at
    ids = json.loads(resumed.stdout)
    # the Markdown report: in this machine's cache of the home, not in a local folder `s3:` of the cwd
    assert Path(ids["report_file"]).is_relative_to(tmp_path / "driver-cache"), ids["report_file"]
    outcomes = _steps(resumed.stderr)
    assert "failed" not in outcomes.values(), resumed.stderr[-3000:]
    assert not WARNING.search(resumed.stderr), resumed.stderr[-3000:]  # e.g. a cache entry refused
    assert all(outcomes[s] == "cached" for s in killed), "a step committed before the kill ran again"
    assert any(o == "done" for s, o in outcomes.items() if s.startswith("draw")), "nothing left to resume"

    _wait_idle(address)  # the killed driver's last task on the cluster may commit after the resume
    assert run_cli("catalogue", "verify", home=home, env=cache).returncode == 0  # rows == objects
    assert run_cli("verify", "--all", home=home, env=cache).returncode == 0  # every byte re-hashed

    monkeypatch.setenv("CAPVECTOR_CACHE", cache["CAPVECTOR_CACHE"])
    api = ArtifactsAPI(home, catch_up=False)
    _, keys = api.query_rows(
        "SELECT json_extract_string(config, '$.cache_key') AS k, count(*) FROM artifacts "
        "WHERE k IS NOT NULL GROUP BY k"  # snapshots and adapters, registered beside a result, have none
    )
    assert [k for k, n in keys if n > 1] == [], "a step's result was committed twice, differently"
    assert len(keys) == len(outcomes)  # one result per planned step

    report = StudyReport.model_validate(api.store.open_json(ids["report"]))
    differences = golden_differences(report)
    assert not differences, "\n".join(differences[:20])
    print(f"killed after {killed_at:.0f} s, {len(killed)} steps reported; resumed in {resumed_s:.0f} s")
