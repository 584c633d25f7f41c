"""`capvector evaluate --runner dask`: evaluations fan out to Dask worker processes, which write the
scores to the catalogue themselves."""

import json

from conftest import run_cli

from capvector.artifacts.api import ArtifactsAPI

TASK = "button-press-topdown-v3"


def test_dask_evaluation_of_two_checkpoints(smoke_home):
    home, ids = smoke_home
    checkpoints = [ids["checkpoints"]["sft/seed0"], ids["checkpoints"]["capvector/seed0"]]
    api = ArtifactsAPI(str(home))
    before = set(api.query("SELECT DISTINCT evaluation_id FROM eval_tasks")["evaluation_id"])

    stdout = run_cli(
        "evaluate", checkpoints[0][:12], checkpoints[1],
        "--tasks", TASK, "--episodes", "2", "--horizon", "40",
        "--runner", "dask", "--workers", "2", "--json",
        home=home,
    ).stdout  # fmt: skip
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
