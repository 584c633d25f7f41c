"""`capvector evaluate --runner dask`: evaluations fan out to Dask worker processes, which write the
scores to the catalogue themselves."""

import json
import os
import signal
import subprocess
import sys

from conftest import REPO

from artifacts.api import ArtifactsAPI

TASK = "button-press-topdown-v3"


def _run_cli_to_files(*args: str, home, tmp_path) -> str:
    """`capvector ARGS` with its output in files, not pipes: a helper process that outlives the command
    (Prefect's ephemeral API server has been seen to) cannot hold the test up; it is stopped after."""
    out, err = tmp_path / "stdout", tmp_path / "stderr"
    env = {**os.environ, "CAPVECTOR_HOME": str(home), "CAPVECTOR_QUIET": "1"}
    with out.open("wb") as o, err.open("wb") as e:
        proc = subprocess.Popen(
            [sys.executable, "-m", "flows.cli", *args],
            cwd=REPO,
            env=env,
            stdout=o,
            stderr=e,
            start_new_session=True,
        )
        try:
            rc = proc.wait(timeout=900)
        finally:
            try:
                os.killpg(proc.pid, signal.SIGKILL)  # leftovers in the session this test started
            except ProcessLookupError:
                pass
    assert rc == 0, f"capvector {' '.join(args)} failed ({rc}):\n{err.read_text()[-3000:]}"
    return out.read_text()


def test_dask_evaluation_of_two_checkpoints(smoke_home, tmp_path):
    home, ids = smoke_home
    checkpoints = [ids["checkpoints"]["sft/seed0"], ids["checkpoints"]["capvector/seed0"]]
    api = ArtifactsAPI(str(home))
    before = set(api.query("SELECT DISTINCT evaluation_id FROM eval_tasks")["evaluation_id"])

    stdout = _run_cli_to_files(
        "evaluate", checkpoints[0][:12], checkpoints[1],
        "--tasks", TASK, "--episodes", "2", "--horizon", "40",
        "--runner", "dask", "--workers", "2", "--json",
        home=home, tmp_path=tmp_path,
    )  # fmt: skip
    rows = json.loads(stdout)
    assert [r["checkpoint"] for r in rows] == checkpoints
    evaluations = [r["evaluation"] for r in rows]
    assert len(set(evaluations)) == 2 and not set(evaluations) & before  # new protocol: new evaluations

    frame = api.query(
        "SELECT evaluation_id, checkpoint_id, task, n_episodes, success_rate, fingerprint FROM eval_tasks "
        "WHERE evaluation_id IN (?, ?) ORDER BY checkpoint_id",
        evaluations,
    )
    assert sorted(frame.itertuples(index=False)) == sorted(
        (r["evaluation"], r["checkpoint"], TASK, 2, r["success_rates"][TASK], frame.fingerprint[0])
        for r in rows
    )
    assert frame.fingerprint.nunique() == 1  # one protocol for both checkpoints
    episodes = api.query(
        "SELECT evaluation_id, count(*) AS n, avg(success::INT) AS rate, max(steps) AS steps "
        "FROM eval_episodes "
        "WHERE evaluation_id IN (?, ?) GROUP BY evaluation_id",
        evaluations,
    )
    for r in episodes.itertuples():
        assert r.n == 2 and r.steps <= 40
        assert r.rate == next(x["mean_success"] for x in rows if x["evaluation"] == r.evaluation_id)
    for r in rows:
        record = api.get(r["evaluation"])
        parents = api.query("SELECT parent FROM edges WHERE child = ?", [record.id])["parent"].tolist()
        assert r["checkpoint"] in parents
