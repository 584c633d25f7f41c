"""Lineage queries against a plain reference: a breadth-first walk in Python over the edges table.

Diamond-shaped histories (one artifact reached along many paths) are where a recursive query can go
wrong: rows multiplied per path, a node at a longer distance than its shortest, an edge among the
returned nodes missing. The reference is written for clarity, not speed.
"""

import random
import subprocess
import sys
from pathlib import Path

import duckdb
import pytest

from capvector.artifacts import catalogue as catalogue_mod
from capvector.artifacts.api import ArtifactsAPI
from capvector.artifacts.catalogue import Catalogue, LineageNode


def reference(edges, start, ancestors, max_depth=None):
    """{id: depth} at the shortest distance, every edge among those nodes and the start, and each
    node's path: that of the smallest (near end, role) edge from a node one step nearer, extended."""
    near, far = (1, 0) if ancestors else (0, 1)
    depth, frontier = {start: 0}, [start]
    while frontier and (max_depth is None or depth[frontier[0]] < max_depth):
        nxt = []
        for node in frontier:
            for e in edges:
                if e[near] == node and e[far] not in depth:
                    depth[e[far]] = depth[node] + 1
                    nxt.append(e[far])
        frontier = sorted(set(nxt))
    links = {e for e in edges if e[0] in depth and e[1] in depth}
    paths = {start: ([start], [])}
    for node in sorted((n for n in depth if n != start), key=lambda n: (depth[n], n)):
        hops = [(e[near], e[2]) for e in links if e[far] == node and depth[e[near]] == depth[node] - 1]
        via, role = min(hops)
        paths[node] = (paths[via][0] + [node], paths[via][1] + [role])
    del depth[start]
    return depth, links, paths


def layered_dag(n, generations, seed):
    """Each artifact has 1-3 parents among the previous two generations, some joined by two roles:
    diamonds everywhere."""
    rng = random.Random(seed)
    ids = [f"{i:064x}" for i in range(n)]
    per = n // generations
    edges = set()
    for g in range(1, generations):
        pool = ids[max(0, (g - 2) * per) : g * per]
        for child in ids[g * per : (g + 1) * per]:
            for parent in rng.sample(pool, rng.randint(1, 3)):
                for role in rng.sample(["init", "base", "vector", "data"], rng.choice([1, 1, 2])):
                    edges.add((parent, child, role))
    return ids, sorted(edges)


@pytest.fixture(scope="module")
def dag(tmp_path_factory):
    """A real catalogue file holding a layered DAG; a few parents have no artifacts row (kind None)."""
    ids, edges = layered_dag(300, 10, seed=3)
    cat = Catalogue(tmp_path_factory.mktemp("dag") / "catalogue.duckdb")
    con = duckdb.connect(str(cat.path))
    con.executemany(
        "INSERT INTO artifacts (id, kind, name, layout, size_bytes, n_files) VALUES (?, ?, ?, 'file', 1, 1)",
        [(i, "checkpoint", f"a{k}") for k, i in enumerate(ids) if k % 17],
    )
    con.executemany("INSERT INTO edges (parent, child, role) VALUES (?, ?, ?)", edges)
    con.close()
    names = {i: ("checkpoint", f"a{k}") if k % 17 else (None, None) for k, i in enumerate(ids)}
    return cat, ids, edges, names


@pytest.mark.parametrize("max_depth", [None, 1, 2, 5])
@pytest.mark.parametrize("ancestors", [True, False])
def test_walk_matches_the_reference_on_a_diamond_shaped_dag(dag, ancestors, max_depth):
    cat, ids, edges, names = dag
    starts = ids[-3:] if ancestors else ids[:3]
    for start in starts + [ids[150]]:
        rows = (cat.ancestors if ancestors else cat.descendants)(start, max_depth)
        depth, links, paths = reference(edges, start, ancestors, max_depth)
        assert depth  # the walk went somewhere
        assert [r.id for r in rows] == sorted(depth, key=lambda n: (depth[n], n))
        assert {r.id: r.depth for r in rows} == depth
        assert {r.id: (r.kind, r.name) for r in rows} == {n: names[n] for n in depth}
        got = [link for r in rows for link in r.links]
        assert len(got) == len(set(got)) and set(got) == links
        for r in rows:  # each edge belongs to the node at its end away from the start, sorted
            assert all(link[0 if ancestors else 1] == r.id for link in r.links)
            assert r.links == sorted(r.links)
            assert (r.path, r.roles) == paths[r.id]


def test_diamond_through_the_api(tmp_path):
    """data → pt, pt → ft and ao (two paths), both → gamma, pt and gamma → meta: each node once, at
    its shortest distance, with every edge among them."""
    api = ArtifactsAPI(tmp_path / "home")
    data = api.register_json({"d": 1}, "dataset", "data").id
    pt = api.register_json({"w": "pt"}, "checkpoint", "pt", parents=[(data, "data")]).id
    ft = api.register_json({"w": "ft"}, "checkpoint", "ft", parents=[(pt, "init")]).id
    ao = api.register_json({"w": "ao"}, "checkpoint", "ao", parents=[(pt, "init")]).id
    gamma = api.register_json({"g": 1}, "vector", "gamma", parents=[(ao, "minuend"), (ft, "subtrahend")]).id
    meta = api.register_json({"w": "m"}, "checkpoint", "meta", parents=[(pt, "base"), (gamma, "vector")]).id
    edges = api.query("SELECT parent, child, role FROM edges").values.tolist()
    edges = [tuple(e) for e in edges]
    for start, ancestors in [(meta, True), (data, False), (pt, False), (gamma, True)]:
        rows = api.ancestors(start) if ancestors else api.descendants(start)
        depth, links, paths = reference(edges, start, ancestors)
        assert {r.id: r.depth for r in rows} == depth
        assert {link for r in rows for link in r.links} == links
        assert {r.id: (r.path, r.roles) for r in rows} == {n: paths[n] for n in depth}
    by_id = {r.id: r for r in api.ancestors(meta[:10])}
    assert by_id[pt].depth == 1 and by_id[pt].roles == ["base"] and by_id[data].depth == 2
    assert set(by_id[pt].links) == {(pt, meta, "base"), (pt, ft, "init"), (pt, ao, "init")}


def test_unvalidated_nodes_equal_validated_ones(dag):
    """Nodes are built without pydantic's validation: they must be indistinguishable from validated
    ones (equality, dumps, copies, assignment)."""
    cat, ids, _, _ = dag
    rows = cat.descendants(ids[0])
    assert rows
    for r in rows:
        assert type(r) is LineageNode
        assert LineageNode.model_validate(r.model_dump()) == r
        assert r.model_dump_json() == LineageNode(**r.model_dump()).model_dump_json()
        assert r.model_fields_set == set(LineageNode.model_fields)
    copy = rows[0].model_copy(update={"depth": 99})
    assert copy.depth == 99 and rows[0].depth != 99
    rows[1].name = "renamed"
    assert rows[1].name == "renamed" and rows[2].name != "renamed"


def test_reads_are_read_only_and_see_other_processes_writes(dag, tmp_path):
    """The lookups attach the file read-only to a process-wide database for one unit of work: they
    cannot write, hold no lock afterwards, and see what another process committed since."""
    cat, ids, _, _ = dag
    path = tmp_path / "c.duckdb"
    path.write_bytes(cat.path.read_bytes())
    copy = Catalogue(path)
    with pytest.raises(duckdb.Error):
        copy._lookup(lambda con: con.execute("INSERT INTO runs (flow_run_id, flow_name) VALUES ('r', 'f')"))
    before = {r.id for r in copy.descendants(ids[-1])}
    new = "f" * 64
    code = (
        "import duckdb, sys; c = duckdb.connect(sys.argv[1]); "
        "c.execute('INSERT INTO edges VALUES (?, ?, ?, NULL)', [sys.argv[2], sys.argv[3], 'init']); c.close()"
    )
    subprocess.run([sys.executable, "-c", code, str(path), ids[-1], new], check=True, timeout=120)
    assert before == set() and [r.id for r in copy.descendants(ids[-1])] == [new]
    assert copy.query("SELECT count(*) n FROM runs")["n"][0] == 0


def test_a_lineage_command_exits_without_duckdb_leak_report(dag):
    """The process-wide database is closed at exit: DuckDB's bindings report nothing as leaked."""
    cat, ids, _, _ = dag
    code = (
        "import sys; from capvector.artifacts.catalogue import Catalogue; "
        "print(len(Catalogue(sys.argv[1]).ancestors(sys.argv[2])))"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, str(cat.path), ids[-1]],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=Path(catalogue_mod.__file__).resolve().parent.parent,
    )
    assert proc.returncode == 0 and int(proc.stdout) > 10, proc.stderr
    assert "nanobind" not in proc.stderr and "leaked" not in proc.stderr, proc.stderr[-2000:]
