"""`capvector runs` (the experiment table) and `capvector export` (Parquet files).

A registered home written the way the train step writes (step config under `train_step`, snapshots as
parents with role `snapshot`, a draw named in a parent) checks every column against what was
registered; the smoke home checks the table against a real run; csv, json and parquet must hold the
same values; export's row counts must match the catalogue's.
"""

import csv
import io
import json

import duckdb
import pytest
from conftest import run_cli
from typer.testing import CliRunner

from capvector.artifacts.api import ArtifactsAPI
from capvector.flows.cli.main import app

TEST, TEST_B, VALIDATION, VALIDATION_EXT = "a1" * 32, "c3" * 32, "b2" * 32, "d4" * 32
BASES = {TEST: 100_000, TEST_B: 100_000, VALIDATION: 50_000, VALIDATION_EXT: 50_000}


def train_config(
    seed, steps=30, lr=3e-4, aux=None, orthogonal=None, applied=None, applied_key="lambda_absolute", **extra
):
    step = {
        "adapter": "full",
        "orthogonal": orthogonal,
        "train": {"seed": seed, "lr": lr, "steps": steps, "aux": aux, "snapshot_steps": []},
    }
    summary = {"steps": steps} | ({applied_key: applied} if applied is not None else {})
    return {"train_step": step, "summary": summary, **extra}


def train(api, name, parents, seed=0, snapshots=(), flow_run_id=None, **kw):
    """A run as run_train registers it: its snapshots first, then the final checkpoint naming them."""
    config = train_config(seed, **kw)
    snaps = {}
    for b in snapshots:
        snap_config = {"train_step": config["train_step"], "budget": b, "of_run": f"key {name}"}
        snaps[b] = api.register_json(
            {"w": name, "b": b}, "checkpoint", f"{name} @ {b} steps", snap_config, parents
        ).id
    config["snapshots"] = {str(b): i for b, i in snaps.items()}
    refs = [*parents, *((i, "snapshot", {"budget": b}) for b, i in snaps.items())]
    return api.register_json({"w": name}, "checkpoint", name, config, refs, flow_run_id=flow_run_id).id, snaps


def evaluate(api, checkpoint, fp, per_task, tag=""):
    """An evaluation whose success rate on each task is per_task[task] (4 episodes per task)."""
    episodes = [
        {"task": task, "seed": BASES[fp] + i, "success": i < round(4 * rate), "steps": 10 + i, "return": 1.0}
        for task, rate in per_task.items()
        for i in range(4)
    ]
    doc = {"checkpoint_id": checkpoint, "fingerprint": fp, "episodes": episodes}
    return api.register_evaluation(doc, f"evaluate {checkpoint[:6]}{tag}").id


@pytest.fixture
def home(tmp_path):
    """θ_pt; a draw's θ_ft, θ_ao, γ and θ_meta (α = 0.5); SFT at seeds 0 and 1 (snapshots at 10 and
    20 steps) and CapVector at seed 0 (snapshot at 10); test evaluations of every budget, a later
    re-evaluation of one, validation evaluations of CapVector's final checkpoint and of θ_ao."""
    api = ArtifactsAPI(str(tmp_path / "home"))
    data = api.register_json({"d": 1}, "dataset", "demos downstream").id
    pt, _ = train(api, "pretrain θ_pt", [(data, "data")])
    ao, _ = train(
        api, "draw 1 auxiliary SFT θ_ao", [(pt, "init")], steps=20, aux={"name": "dynamics", "weight": 0.5}
    )
    ft, _ = train(api, "draw 1 standard SFT θ_ft", [(pt, "init")], steps=20)
    gamma = api.register_json(
        {"g": 1}, "vector", "draw 1 capability vector γ", parents=[(ao, "minuend"), (ft, "subtrahend")]
    ).id
    meta = api.register_json(
        {"m": 1},
        "checkpoint",
        "draw 1 merge θ_meta",
        {"alpha": 0.5},
        [(pt, "base"), (gamma, "vector", {"alpha": 0.5})],
    ).id
    ids = {"pt": pt, "ao": ao, "ft": ft, "gamma": gamma, "meta": meta}
    sft = {}
    for seed in (0, 1):
        sft[seed] = train(
            api, f"downstream sft seed {seed}", [(data, "data"), (pt, "init")], seed=seed, snapshots=(10, 20)
        )
        ids[f"sft{seed}"] = sft[seed][0]
    cap, cap_snaps = train(
        api,
        "downstream capvector seed 0",
        [(data, "data"), (meta, "init"), (gamma, "regularized_by")],
        lr=1e-3,
        snapshots=(10,),
        orthogonal={"lambda_absolute": None, "lambda_relative": 0.25},
        applied=0.01,
    )
    ids["cap"] = cap
    for seed, (final, snaps) in sft.items():
        evaluate(api, snaps[10], TEST, {"reach": 0.25, "push": 0.0})
        evaluate(api, snaps[20], TEST, {"reach": 0.5, "push": 0.25})
        evaluate(api, final, TEST, {"reach": 0.75, "push": 0.5 if seed == 0 else 0.25})
    evaluate(api, sft[0][0], TEST, {"reach": 1.0, "push": 0.5}, tag=" again")  # the latest counts
    evaluate(api, cap_snaps[10], TEST, {"reach": 0.5, "push": 0.5})
    evaluate(api, cap, TEST, {"reach": 1.0, "push": 0.75})
    evaluate(api, cap, VALIDATION, {"reach": 0.0, "push": 0.25})
    evaluate(api, ao, VALIDATION_EXT, {"drawer": 0.5})  # validation on other tasks (D_ext)
    return tmp_path / "home", ids


def invoke(home, *args):
    result = CliRunner().invoke(app, ["--home", str(home), *args])
    assert result.exit_code == 0, (result.output, result.exception)
    return result


def rows_json(home, *args):
    return {r["name"]: r for r in json.loads(invoke(home, "runs", "--format", "json", *args).stdout)}


def test_runs_recorded_before_lambda_had_two_names_show_it_under_the_new_ones(home):
    """A run recorded with `orthogonal.weight` + `scale` and a summary's `orthogonal_lambda` (the names
    until 2026-11) reads as lambda_relative / lambda_absolute."""
    home, ids = home
    api = ArtifactsAPI(str(home))
    old = {"weight": 0.5, "scale": "action_gradient"}
    data = api.register_json({"d": 2}, "dataset", "demos downstream 2").id
    train(api, "downstream capvector seed 1", [(data, "data"), (ids["meta"], "init")], seed=1,
          orthogonal=old, applied=0.02, applied_key="orthogonal_lambda")  # fmt: skip
    row = rows_json(home)["downstream capvector seed 1"]
    assert (row["lambda_relative"], row["lambda_absolute"]) == (0.5, 0.02)


def test_every_trained_run_once_with_its_settings_and_success_per_budget_and_task(home):
    home, ids = home
    rows = rows_json(home)
    assert sorted(rows) == sorted(
        [
            "pretrain θ_pt",
            "draw 1 auxiliary SFT θ_ao",
            "draw 1 standard SFT θ_ft",
            "downstream sft seed 0",
            "downstream sft seed 1",
            "downstream capvector seed 0",
        ]
    )  # snapshots and the merged θ_meta are no runs
    cap = rows["downstream capvector seed 0"]
    assert cap["id"] == ids["cap"]
    assert (cap["stage"], cap["arm"], cap["draw"], cap["seed"]) == ("downstream", "capvector", 1, 0)
    assert (cap["alpha"], cap["lambda_relative"], cap["lambda_absolute"]) == (0.5, 0.25, 0.01)
    assert (cap["lr"], cap["adapter"], cap["steps"]) == (1e-3, "full", 30)
    assert (cap["success@10"], cap["reach@10"], cap["push@10"]) == (0.5, 0.5, 0.5)
    assert (cap["success@30"], cap["reach@30"], cap["push@30"]) == (0.875, 1.0, 0.75)  # test, not validation
    assert cap["success@20"] is None  # no snapshot at 20
    sft0, sft1 = rows["downstream sft seed 0"], rows["downstream sft seed 1"]
    assert (sft0["arm"], sft0["draw"], sft0["seed"], sft1["seed"], sft0["alpha"]) == ("sft", None, 0, 1, None)
    assert (sft0["reach@10"], sft0["reach@20"], sft0["reach@30"]) == (0.25, 0.5, 1.0)  # @30: re-evaluated
    assert sft1["push@30"] == 0.25 and sft1["success@20"] == 0.375
    ao = rows["draw 1 auxiliary SFT θ_ao"]
    assert (ao["stage"], ao["arm"], ao["draw"], ao["aux"], ao["aux_weight"]) == (
        "extraction",
        "θ_ao",
        1,
        "dynamics",
        0.5,
    )
    assert rows["pretrain θ_pt"]["stage"] == "pretrain" and rows["pretrain θ_pt"]["success@30"] is None

    validation = rows_json(home, "--fingerprint", "validation")
    assert validation["downstream capvector seed 0"]["success@30"] == 0.125
    assert validation["draw 1 auxiliary SFT θ_ao"]["drawer@20"] == 0.5  # both validation protocols
    assert validation["downstream sft seed 0"]["success@30"] is None
    assert rows_json(home, "--fingerprint", VALIDATION[:8]).keys() == validation.keys()

    table = invoke(home, "runs").stdout
    assert "87.5%" in table and f"protocol {TEST[:12]} test" in table and ids["cap"][:12] in table


def test_a_studys_per_draw_and_per_replicate_runs_get_their_arm_draw_study_and_status(home):
    """Issue 37: `downstream sft_from_ao draw 0 seed 0` and `downstream capvector replicate 0 seed 1` are
    downstream runs of their arm, draw or replicate (not `other`); a run is labelled with the study its
    flow run ran (or whose analysis has it in its lineage), that run's state and its training time."""
    from capvector.artifacts.records import RunRecord

    home, ids = home
    api = ArtifactsAPI(str(home))
    flow_run = {"flow_run_id": "f-1", "flow_name": "study", "parameters": {"config": {"name": "demo"}}}
    api.record_run(RunRecord(**flow_run, state="COMPLETED"))
    from_ao, _ = train(api, "downstream sft_from_ao draw 1 seed 0", [(ids["ao"], "init")], flow_run_id="f-1")
    meta = api.register_json({"m": 2}, "checkpoint", "replicate 0 merge θ_meta", {}, [(ids["pt"], "base")]).id
    rep, _ = train(api, "downstream capvector replicate 0 seed 1", [(meta, "init")], seed=1)
    evaluation = evaluate(api, rep, TEST, {"reach": 1.0})
    api.register_json({"s": 1}, "study", "analyse study other-study (gate)", {}, [(evaluation, "test")])
    rows = rows_json(home)
    got = {k: rows["downstream sft_from_ao draw 1 seed 0"][k] for k in ("stage", "arm", "draw", "study")}
    assert got == {"stage": "downstream", "arm": "sft_from_ao", "draw": 1, "study": "demo"}
    assert rows["downstream sft_from_ao draw 1 seed 0"]["status"] == "COMPLETED"
    cap = rows["downstream capvector replicate 0 seed 1"]
    assert (cap["stage"], cap["arm"], cap["replicate"], cap["draw"], cap["seed"]) == (
        "downstream", "capvector", 0, None, 1
    )  # fmt: skip
    assert cap["study"] == "other-study" and cap["status"] is None
    assert rows_json(home, "--arm", "sft_from_ao").keys() == {"downstream sft_from_ao draw 1 seed 0"}
    assert rows_json(home, "--stage", "other") == {}


def test_every_run_names_the_code_revision_that_trained_it(home, tmp_path, monkeypatch):
    """Issue 37: a result is traced to the code that made it: `code_revision` is the `git describe` the
    run's record keeps (`code_version`), in the table, its json and the exported runs."""
    from capvector.artifacts import store

    home, ids = home
    api = ArtifactsAPI(str(home))
    monkeypatch.setattr(store, "code_version", lambda: "git:v0.9-3-gabc1234")
    older, _ = train(api, "downstream sft seed 7", [(ids["pt"], "init")], seed=7)
    rows = rows_json(home)
    assert rows["downstream sft seed 7"]["code_revision"] == "git:v0.9-3-gabc1234"
    for row in rows.values():
        assert row["code_revision"] == api.get(row["id"]).code_version
    current = rows["downstream capvector seed 0"]["code_revision"]
    assert current and current != "git:v0.9-3-gabc1234"
    table = invoke(home, "runs").stdout.splitlines()
    header = table[0].split()
    assert header[header.index("train_s") + 1] == "code_revision"
    assert any(line.startswith(older[:12]) and " git:v0.9-3-gabc1234 " in line for line in table)
    invoke(home, "export", str(tmp_path / "export"))
    exported = duckdb.connect().execute(
        f"SELECT id, code_revision FROM read_parquet('{tmp_path / 'export' / 'runs.parquet'}')"
    )
    assert dict(exported.fetchall()) == {r["id"]: r["code_revision"] for r in rows.values()}


def test_filters(home):
    home, _ = home
    assert set(rows_json(home, "--arm", "sft")) == {"downstream sft seed 0", "downstream sft seed 1"}
    assert len(rows_json(home, "--arm", "sft,capvector")) == 3
    assert set(rows_json(home, "--kind", "extraction")) == {
        "draw 1 auxiliary SFT θ_ao",
        "draw 1 standard SFT θ_ft",
    }
    assert set(rows_json(home, "--where", 'seed = 1 OR "success@30" > 0.8')) == {
        "downstream sft seed 1",
        "downstream capvector seed 0",
    }
    means = rows_json(home, "--means-only")["downstream sft seed 0"]
    assert "success@30" in means and "reach@30" not in means


def test_csv_json_and_parquet_hold_the_same_table(home, tmp_path):
    home, _ = home
    as_json = json.loads(invoke(home, "runs", "--format", "json").stdout)
    assert as_json
    columns = list(as_json[0])
    text = invoke(home, "runs", "--format", "csv").stdout
    invoke(home, "runs", "--format", "csv", "-o", str(tmp_path / "runs.csv"))
    assert (tmp_path / "runs.csv").read_text() == text
    read = list(csv.DictReader(io.StringIO(text)))
    assert list(read[0]) == columns and len(read) == len(as_json)
    for got, want in zip(read, as_json, strict=True):
        for column, value in want.items():
            if value is None:
                assert got[column] == ""
            elif isinstance(value, int | float):
                assert float(got[column]) == pytest.approx(value), column
            else:
                assert got[column] == str(value), column

    out = tmp_path / "runs.parquet"
    printed = invoke(home, "runs", "--format", "parquet", "-o", str(out)).stdout
    assert f"wrote {out}: {len(as_json)} runs" in printed
    con = duckdb.connect()
    result = con.execute(f"SELECT * FROM read_parquet('{out}')")
    names = [d[0] for d in result.description]
    parquet = [dict(zip(names, r, strict=True)) for r in result.fetchall()]
    assert names == columns
    for got, want in zip(parquet, as_json, strict=True):
        for column, value in want.items():
            if column == "created_at":
                assert str(got[column]) == value
            elif isinstance(value, float):
                assert got[column] == pytest.approx(value), column
            else:
                assert got[column] == value, column


def test_a_column_never_mixes_protocols(home):
    home, ids = home
    api = ArtifactsAPI(str(home))
    evaluate(api, ids["ft"], TEST_B, {"reach": 1.0})  # another test-goal protocol, a task in common
    result = CliRunner().invoke(app, ["--home", str(home), "runs", "--fingerprint", "test"])  # asked: both
    assert result.exit_code != 0 and "task reach was evaluated under 2" in str(result.exception)
    table = invoke(home, "runs").stdout  # one protocol per table unless asked: the most evaluated one
    assert f"protocol {TEST[:12]} test" in table and f"not shown: {TEST_B[:12]} test" in table
    rows = rows_json(home, "--fingerprint", TEST_B[:8])
    assert rows["draw 1 standard SFT θ_ft"]["reach@20"] == 1.0 and "push@30" not in rows["pretrain θ_pt"]
    bad = CliRunner().invoke(app, ["--home", str(home), "runs", "--fingerprint", "ffffff"])
    assert bad.exit_code != 0 and "matches no evaluation protocols" in str(bad.exception)


def test_export_writes_episodes_evaluations_and_runs(home, tmp_path):
    home, ids = home
    out = tmp_path / "export"
    printed = invoke(home, "export", str(out)).stdout
    con = duckdb.connect()
    n_eps, n_tasks, n_evals = con.execute(
        f"SELECT sum(n_episodes), count(*), count(DISTINCT evaluation_id) FROM "
        f"read_parquet('{out / 'evaluations.parquet'}')"
    ).fetchone()
    api = ArtifactsAPI(str(home))
    _, [(catalogued_eps, catalogued_tasks)] = api.query_rows(
        "SELECT (SELECT count(*) FROM eval_episodes), (SELECT count(*) FROM eval_tasks)"
    )
    assert n_eps == catalogued_eps == 4 * n_tasks and n_tasks == catalogued_tasks and n_evals == 11
    episodes = con.execute(
        f"SELECT evaluation_id, checkpoint_id, run_id, budget, task, goal_seed, success, steps, protocol "
        f"FROM read_parquet('{out / 'episodes.parquet'}')"
    ).fetchall()
    assert len(episodes) == n_eps
    assert {(r[2], r[3]) for r in episodes if r[1] == ids["cap"]} == {(ids["cap"], 30)}
    assert {r[8] for r in episodes} == {"test", "validation"} and min(r[5] for r in episodes) == 50_000
    runs = con.execute(f"SELECT name FROM read_parquet('{out / 'runs.parquet'}')").fetchall()
    assert len(runs) == 6
    assert f"wrote {out / 'episodes.parquet'}: {n_eps} rows" in printed
    assert not list(out.glob(".*tmp"))  # written atomically: no temporary file left


def test_runs_on_a_real_home(smoke_home, tmp_path):
    """Every checkpoint the train step produced is one row, with its arm, seed and lr, and the success
    of its evaluation; export's episodes are the evaluations' episodes."""
    home, ids = smoke_home
    api = ArtifactsAPI(str(home))
    # other tests evaluate the shared smoke home under other protocols (another horizon, a video):
    # the table is asked for the preset's own
    _, (fingerprint,) = api.query_rows(
        "SELECT DISTINCT fingerprint FROM eval_tasks WHERE evaluation_id = ?",
        [ids["evaluations"]["sft/seed0"]],
    )
    protocol = ["--fingerprint", fingerprint[0][:12]]
    rows = json.loads(run_cli("runs", "--format", "json", *protocol, home=home).stdout)
    _, trained = api.query_rows(
        "SELECT id, config->'train_step'->'train' FROM artifacts WHERE kind = 'checkpoint' "
        "AND (config->'train_step') IS NOT NULL AND (config->>'of_run') IS NULL"
    )
    assert sorted(r["id"] for r in rows) == sorted(t[0] for t in trained)
    by_id = {r["id"]: r for r in rows}
    for checkpoint_id, train_config in trained:
        train_config = json.loads(train_config)
        row = by_id[checkpoint_id]
        assert (row["seed"], row["lr"], row["steps"]) == (
            train_config["seed"],
            train_config["lr"],
            train_config["steps"],
        )
    for label, checkpoint_id in ids["checkpoints"].items():
        arm, seed = label.split("/seed")
        row = by_id[checkpoint_id]
        assert (row["stage"], row["arm"], row["seed"]) == ("downstream", arm, int(seed))
        _, tasks = api.query_rows(
            "SELECT task, success_rate FROM eval_tasks WHERE checkpoint_id = ? AND fingerprint = ?",
            [checkpoint_id, fingerprint[0]],
        )
        assert tasks
        for task, rate in tasks:
            assert row[f"{task}@{row['steps']}"] == rate
        assert row[f"success@{row['steps']}"] == pytest.approx(sum(r for _, r in tasks) / len(tasks))
    assert by_id[ids["checkpoints"]["capvector/seed0"]]["alpha"] is not None

    out = tmp_path / "export"
    run_cli("export", str(out), *protocol, home=home)
    con = duckdb.connect()
    [(n_eps,)] = con.execute(f"SELECT count(*) FROM read_parquet('{out / 'episodes.parquet'}')").fetchall()
    _, [(want,)] = api.query_rows("SELECT sum(n_episodes) FROM eval_tasks")
    assert n_eps == want
    [(n_runs,)] = con.execute(f"SELECT count(*) FROM read_parquet('{out / 'runs.parquet'}')").fetchall()
    assert n_runs == len(rows)
