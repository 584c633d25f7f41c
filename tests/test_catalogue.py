"""The DuckDB catalogue: lineage queries, scores, rebuild from the store, migrations, read-only SQL."""

import re
import shutil

import duckdb
import pytest

from capvector.artifacts.api import ArtifactsAPI
from capvector.artifacts.catalogue import Catalogue
from capvector.artifacts.errors import MixedFingerprints, ReadOnlyViolation, SchemaTooNew, UnknownParent
from capvector.artifacts.records import RunRecord
from capvector.artifacts.schema import MIGRATIONS
from capvector.flows.views.lineage import as_mermaid, as_tree

TABLES = ["artifacts", "edges", "vector_stats", "eval_episodes", "eval_tasks", "runs"]


def episodes(task, successes):
    return [
        {
            "task": task,
            "seed": i,
            "success": s,
            "steps": 10 + i,
            "return": float(s),
            "video": f"{task}-{i}.mp4",
        }
        for i, s in enumerate(successes)
    ]


@pytest.fixture(scope="module")
def template(tmp_path_factory):
    """The CapVector pipeline in miniature: data → θ_pt → θ_ft/θ_ao → γ → θ_meta → downstream → evals."""
    api = ArtifactsAPI(tmp_path_factory.mktemp("template") / "home")
    ids = {}
    ids["demos"] = api.register_json({"demos": 1}, "dataset", "D_ext").id
    ids["down"] = api.register_json({"demos": 2}, "dataset", "D_down").id
    ids["pt"] = api.register_json({"w": "pt"}, "checkpoint", "theta_pt", parents=[(ids["demos"], "data")]).id
    ids["ft"] = api.register_json({"w": "ft"}, "checkpoint", "theta_ft", parents=[(ids["pt"], "init")]).id
    ids["ao"] = api.register_json({"w": "ao"}, "checkpoint", "theta_ao", parents=[(ids["pt"], "init")]).id
    ids["gamma"] = api.register_json(
        {"w": "gamma"}, "vector", "gamma", parents=[(ids["ao"], "minuend"), (ids["ft"], "subtrahend")]
    ).id
    ids["meta"] = api.register_json(
        {"w": "meta"},
        "checkpoint",
        "theta_meta",
        parents=[(ids["pt"], "base"), (ids["gamma"][:8], "vector", {"alpha": 1.1})],
    ).id
    ids["sft"] = api.register_json(
        {"w": "sft"},
        "checkpoint",
        "sft_orth",
        parents=[(ids["meta"], "init"), (ids["down"], "data")],
        flow_run_id="run-1",
    ).id
    ids["stats"] = api.register_vector_stats(
        ids["gamma"], [{"tensor": "blocks.0.w", "group": "attn", "numel": 16, "l2": 0.5, "kurtosis": 3.2}]
    ).id
    ids["eval_sft"] = api.register_evaluation(
        {
            "checkpoint_id": ids["sft"],
            "fingerprint": "fpA",
            "library_versions": {"mujoco": "3.3.0"},
            "episodes": episodes("reach-v3", [True, True, False, True]) + episodes("push-v3", [False, True]),
        },
        "eval sft",
        config={"split": "test"},
    ).id
    ids["eval_pt"] = api.register_evaluation(
        {"checkpoint_id": ids["pt"], "fingerprint": "fpA", "episodes": episodes("reach-v3", [False, True])},
        "eval pt",
    ).id
    ids["eval_pt_b"] = api.register_evaluation(
        {"checkpoint_id": ids["pt"], "fingerprint": "fpB", "episodes": episodes("reach-v3", [True])},
        "eval pt b",
    ).id
    api.record_run(RunRecord(flow_run_id="run-1", flow_name="capvector", parameters={"alpha": 1.1}))
    api.record_run(
        RunRecord(flow_run_id="run-1", flow_name="capvector", parameters={"alpha": 1.1}, state="DONE")
    )
    return api.home, ids


@pytest.fixture
def world(template, tmp_path):
    """A private copy of the template home (built once per module: registrations cost a DuckDB open each)."""
    home, ids = template
    shutil.copytree(home, tmp_path / "home")
    return ArtifactsAPI(tmp_path / "home"), ids


def snapshot(api, ids):
    """Every table plus every lineage answer, in a comparable form."""
    tables = {t: api.query(f"SELECT * FROM {t} ORDER BY ALL").astype(str).values.tolist() for t in TABLES}
    lineage = {
        k: (
            [r.model_dump() for r in api.ancestors(v)],
            [r.model_dump() for r in api.descendants(v)],
            [r.model_dump() for r in api.vectors_merged_into(v)],
        )
        for k, v in ids.items()
    }
    return tables, lineage, [s.model_dump() for s in api.scores(ids["demos"], "fpA")]


def test_ancestors_with_depth_and_role_path(world):
    api, ids = world
    anc = {r.id: r for r in api.ancestors(ids["eval_sft"][:8])}
    assert set(anc) == {ids[k] for k in ["sft", "meta", "down", "pt", "gamma", "demos", "ao", "ft"]}
    assert anc[ids["sft"]].depth == 1 and anc[ids["sft"]].roles == ["checkpoint"]
    assert anc[ids["gamma"]].depth == 3 and anc[ids["gamma"]].roles == ["checkpoint", "init", "vector"]
    assert anc[ids["gamma"]].path == [ids["eval_sft"], ids["sft"], ids["meta"], ids["gamma"]]
    assert anc[ids["pt"]].depth == 3  # via meta's base edge, the shortest of its paths
    assert anc[ids["demos"]].kind == "dataset" and anc[ids["demos"]].name == "D_ext"
    assert {r.id for r in api.ancestors(ids["eval_sft"], max_depth=2)} == {
        ids["sft"],
        ids["meta"],
        ids["down"],
    }
    assert api.ancestors(ids["demos"]) == []


def test_descendants_and_vectors_merged(world):
    api, ids = world
    desc = {r.id: r for r in api.descendants(ids["gamma"])}
    assert set(desc) == {ids[k] for k in ["meta", "sft", "stats", "eval_sft"]}
    assert desc[ids["eval_sft"]].roles == ["vector", "init", "checkpoint"]
    assert len(api.descendants(ids["demos"])) == len(ids) - 2  # all but itself and D_down
    merged = api.vectors_merged_into(ids["eval_sft"])
    assert [(m.vector_id, m.merged_into, m.alpha, m.depth) for m in merged] == [
        (ids["gamma"], ids["meta"], 1.1, 3)
    ]
    assert api.vectors_merged_into(ids["ao"]) == []


def test_scores_under_one_fingerprint(world):
    api, ids = world
    with pytest.raises(MixedFingerprints, match="fpA, fpB"):
        api.scores(ids["demos"])
    rows = api.scores(ids["demos"], fingerprint="fpA")
    got = {(r.checkpoint_id, r.task): (r.success_rate, r.n_episodes, r.depth) for r in rows}
    assert got == {
        (ids["pt"], "reach-v3"): (0.5, 2, 1),
        (ids["sft"], "reach-v3"): (0.75, 4, 3),
        (ids["sft"], "push-v3"): (0.5, 2, 3),
    }
    assert [r.success_rate for r in api.scores(ids["pt"], fingerprint="fpB")] == [1.0]
    assert len(api.scores(ids["meta"])) == 2  # only fpA rows below θ_meta: no mixing, no error


def test_side_tables(world):
    api, ids = world
    stats = api.query(
        "SELECT vector_id, tensor, \"group\", numel, l2, extras->>'kurtosis' k FROM vector_stats"
    )
    assert stats.values.tolist() == [[ids["gamma"], "blocks.0.w", "attn", 16, 0.5, "3.2"]]
    ep = api.query("SELECT * FROM eval_episodes WHERE evaluation_id = ? ORDER BY episode", [ids["eval_sft"]])
    assert len(ep) == 6 and ep["return"].tolist()[:2] == [1.0, 1.0] and "video" in ep["extras"][0]
    assert ep["library_versions"][0] == '{"mujoco": "3.3.0"}'
    runs = api.query("SELECT flow_run_id, state, parameters->>'alpha' FROM runs").values.tolist()
    assert runs == [["run-1", "DONE", "1.1"]]
    art = api.query("SELECT flow_run_id FROM artifacts WHERE id = $id", {"id": ids["sft"]})
    assert art.values.tolist() == [["run-1"]]


def test_rebuild_from_store_alone_gives_same_answers(world):
    api, ids = world
    before = snapshot(api, ids)
    api.catalogue.path.unlink()
    fresh = ArtifactsAPI(api.home)
    report = fresh.rebuild()
    assert report.artifacts == len(ids) and report.runs == 1 and report.corrupt == []
    assert snapshot(fresh, ids) == before
    assert fresh.rebuild().artifacts == len(ids)  # rebuilding a full catalogue replaces, never duplicates
    assert snapshot(fresh, ids) == before


def test_sync_indexes_what_the_catalogue_missed(world):
    api, ids = world
    rec = api.store.put_json(
        {"late": True}, "report", "written, then the process died", parents=[(ids["sft"], "data")]
    )
    assert rec.id not in api.query("SELECT id FROM artifacts")["id"].tolist()
    assert api.sync().artifacts == 1
    assert rec.id in {r.id for r in api.descendants(ids["sft"])}
    assert api.sync().artifacts == 0


def test_evaluation_of_unknown_checkpoint_is_refused(world):
    api, _ = world
    count = api.query("SELECT count(*) n FROM artifacts")["n"][0]
    with pytest.raises(UnknownParent, match="deadbeef"):
        api.register_evaluation({"checkpoint_id": "deadbeef" * 8, "fingerprint": "f", "episodes": []}, "e")
    assert api.query("SELECT count(*) n FROM artifacts")["n"][0] == count


@pytest.mark.parametrize(
    "sql",
    [
        "SELECT count(*) FROM artifacts",
        "WITH a AS (SELECT * FROM edges) SELECT * FROM a",
        "SHOW TABLES",
        "DESCRIBE artifacts",
        "EXPLAIN SELECT * FROM runs",
        "PRAGMA table_info('artifacts')",
        "FROM eval_tasks -- a comment; DROP TABLE runs",
    ],
)
def test_read_only_sql_allows_reads(world, sql):
    api, _ = world
    api.query(sql)


@pytest.mark.parametrize(
    "sql",
    [
        "DELETE FROM artifacts",
        "DROP TABLE runs",
        "INSERT INTO runs (flow_run_id, flow_name) VALUES ('x', 'y')",
        "SELECT 1; DROP TABLE runs",
        "COPY artifacts TO '/tmp/leak.csv'",
        "ATTACH '/tmp/other.duckdb'",
        "SET threads = 1",
        "PRAGMA threads = 1",
        "CREATE TEMP TABLE t AS SELECT 1",
        "CHECKPOINT",
        "INSTALL httpfs",
        "not sql at all",
    ],
)
def test_read_only_sql_refuses_everything_else(world, sql):
    api, _ = world
    with pytest.raises(ReadOnlyViolation):
        api.query(sql)
    assert api.query("SELECT count(*) n FROM runs")["n"][0] == 1


def test_read_only_connection_is_the_second_guard(world):
    """Even a statement the parser check let through could not write: the connection is read-only."""
    api, _ = world
    con = duckdb.connect(str(api.catalogue.path), read_only=True)
    with pytest.raises(duckdb.Error):
        con.execute("EXPLAIN ANALYZE DELETE FROM runs")
    con.close()
    with pytest.raises(duckdb.Error, match="[Pp]ermission"):
        api.catalogue._read(lambda c: c.execute("SELECT * FROM read_csv('/etc/hostname')").fetchall())


def test_forward_migration_and_newer_schema(tmp_path):
    path = tmp_path / "c.duckdb"
    Catalogue(path)
    con = duckdb.connect(str(path))
    con.execute("INSERT INTO runs (flow_run_id, flow_name) VALUES ('r', 'f')")
    con.close()
    newer = [*MIGRATIONS, (MIGRATIONS[-1][0] + 1, "ALTER TABLE runs ADD COLUMN note VARCHAR")]
    cat = Catalogue(path, migrations=newer)
    cols = cat.query("DESCRIBE runs")["column_name"].tolist()
    assert "note" in cols and cat.query("SELECT flow_run_id FROM runs").values.tolist() == [["r"]]
    known = MIGRATIONS[-1][0]
    with pytest.raises(SchemaTooNew, match=f"version {known + 1}.*up to version {known}"):
        Catalogue(path)
    with pytest.raises(SchemaTooNew):
        cat.schema_version()  # the default-code read path refuses it too


# ---------------------------------------------------------------------------- lineage views
TREE_LINE = re.compile(
    r"^(?P<indent>(?:│   |    )*)(?:├── |└── )\((?P<role>[^)]*)\) .*?\[(?P<id>[0-9a-f]{12})\]"
)
MERMAID_EDGE = re.compile(
    r'n(?P<a>[0-9a-f]{12})\["[^"]*"\] -->\|(?P<role>[^|]*)\| n(?P<b>[0-9a-f]{12})\["[^"]*"\]$'
)


def tree_edges(text: str, ancestors: bool) -> set[tuple[str, str, str]]:
    """(parent, child, role) of every line of an indented tree, each line read under the line above it."""
    lines = text.splitlines()
    stack = [re.search(r"\[([0-9a-f]{12})\]$", lines[0]).group(1)]
    edges = set()
    for line in lines[1:]:
        m = TREE_LINE.match(line)
        assert m, line
        level = len(m["indent"]) // 4
        del stack[level + 1 :]
        near, far = stack[level], m["id"]
        edges.add((far, near, m["role"]) if ancestors else (near, far, m["role"]))
        stack.append(far)
    return edges


def mermaid_edges(text: str) -> set[tuple[str, str, str]]:
    lines = text.splitlines()
    assert lines[0] in ("graph BT", "graph TD")
    edges = set()
    for line in lines[1:]:
        if line.strip().startswith(("classDef ", "class ")):  # colours by kind
            continue
        m = MERMAID_EDGE.search(line.strip())
        assert m, line
        edges.add((m["a"], m["b"], m["role"]))
    return edges


def test_lineage_views_draw_every_edge_of_the_dag(world):
    """History is a DAG: θ_pt reaches θ_meta directly (base) and through θ_ft, θ_ao and γ; every edge
    is drawn, in the tree (a node repeated as a marked reference) and in Mermaid."""
    api, ids = world
    report = api.register_json(
        {"report": 1},
        "report",
        "report",
        parents=[(ids[k], "evaluation") for k in ("eval_sft", "eval_pt", "eval_pt_b")]
        + [(ids["stats"], "stats")],
    )
    table = {
        (p[:12], c[:12], r) for p, c, r in api.query("SELECT parent, child, role FROM edges").values.tolist()
    }
    cases = [
        (api.get(report.id), True),  # every artifact is an ancestor of the report
        (api.get(ids["demos"]), False),
        (api.get(ids["pt"]), False),
        (api.get(ids["eval_sft"]), True),
        (api.get(ids["gamma"]), False),
    ]
    for root, ancestors in cases:
        rows = api.ancestors(root.id) if ancestors else api.descendants(root.id)
        nodes = {root.id[:12]} | {r.id[:12] for r in rows}
        expected = {e for e in table if e[0] in nodes and e[1] in nodes}
        tree = as_tree(rows, root)
        assert tree_edges(tree, ancestors) == expected, tree
        mermaid = as_mermaid(rows, root, ancestors)
        assert mermaid_edges(mermaid) == expected, mermaid
    everything = as_mermaid(api.ancestors(report.id), api.get(report.id), True)
    assert mermaid_edges(everything) == table and len(table) == 17
    tree = as_tree(api.ancestors(report.id), api.get(report.id))
    assert "↑" in tree  # θ_pt is reached from several children: expanded once, referred to after


def test_lineage_views_within_a_depth_limit(world):
    api, ids = world
    root = api.get(ids["eval_sft"])
    rows = api.ancestors(root.id, max_depth=3)
    nodes = {root.id} | {r.id for r in rows}
    expected = {
        (p[:12], c[:12], r)
        for p, c, r in api.query("SELECT parent, child, role FROM edges").values.tolist()
        if p in nodes and c in nodes
    }
    assert ("theta_pt" in as_tree(rows, root)) and tree_edges(as_tree(rows, root), True) == expected
    assert mermaid_edges(as_mermaid(rows, root, True)) == expected


def test_mermaid_escapes_names(world):
    api, ids = world
    odd = api.register_json(
        {"odd": 1}, "checkpoint", 'say "hi" #1 <b>|x|</b>', parents=[(ids["pt"], 'in"it|x')]
    )
    text = as_mermaid(api.ancestors(odd.id, max_depth=1), api.get(odd.id), True)
    edge = text.splitlines()[1]
    assert edge.count('"') == 4 and "<b>" not in edge, edge
    assert "#quot;hi#quot;" in edge and "#35;1" in edge and "#124;" in edge
    assert mermaid_edges(text) == {(ids["pt"][:12], odd.id[:12], "in#quot;it#124;x")}
    alone = as_mermaid([], api.get(odd.id), True)
    assert alone.splitlines()[1].count('"') == 2
