"""`capvector lineage --kinds/--hide`: only some kinds, with edges contracted through the others.

Checked against a plain reference on a random DAG (kinds mixed, some artifacts without a row): a kept
node is linked to exactly the kept nodes it reaches through hidden ones, ancestry among kept nodes is
what it was, depths count kept hops; and the views draw the contracted edges, coloured by kind, with
hostile names still escaped.
"""

import functools
import hashlib
import random
import re
from types import SimpleNamespace

import duckdb
import pytest
from test_catalogue import mermaid_edges, tree_edges
from typer.testing import CliRunner

from capvector.artifacts.api import ArtifactsAPI
from capvector.artifacts.catalogue import Catalogue
from capvector.flows.cli import inspect_commands
from capvector.flows.cli.main import app
from capvector.flows.views.lineage import CHAIN, as_mermaid, as_tree, keep_kinds, mermaid_lineage

KINDS = ("checkpoint", "vector", "evaluation", "selection", "dataset")


@pytest.fixture(scope="module")
def dag(tmp_path_factory):
    """240 artifacts in 8 generations, 1-3 parents each among the two before; every 13th has no row."""
    rng = random.Random(7)
    ids = [f"{i:064x}" for i in range(240)]
    kinds = {i: (None if k % 13 == 0 else rng.choice(KINDS)) for k, i in enumerate(ids)}
    edges = set()
    for g in range(1, 8):
        pool = ids[max(0, (g - 2) * 30) : g * 30]
        for child in ids[g * 30 : (g + 1) * 30]:
            for parent in rng.sample(pool, rng.randint(1, 3)):
                for role in rng.sample(["init", "base", "vector", "data"], rng.choice([1, 1, 2])):
                    edges.add((parent, child, role))
    cat = Catalogue(tmp_path_factory.mktemp("kinds") / "catalogue.duckdb")
    con = duckdb.connect(str(cat.path))
    con.executemany(
        "INSERT INTO artifacts (id, kind, name, layout, size_bytes, n_files) VALUES (?, ?, ?, 'file', 1, 1)",
        [(i, kinds[i], f"a{k}") for k, i in enumerate(ids) if kinds[i] is not None],
    )
    con.executemany("INSERT INTO edges (parent, child, role) VALUES (?, ?, ?)", sorted(edges))
    con.close()
    return cat, ids, kinds, sorted(edges)


def reference(edges, kinds, root, walked, ancestors, kept_kinds):
    """{(parent, child): roles} of the contracted graph over the kept nodes, by brute force: the roles
    of the direct edges, else one chain per pair when some path joins them through hidden nodes only."""
    kept = {root} | {n for n in walked if kinds[n] in kept_kinds}
    nodes = kept | set(walked)
    out = {}
    for start in kept:
        frontier, seen = [(start, ())], {start}
        while frontier:
            nxt = []
            for node, chain in frontier:
                for p, c, role in edges:
                    if p not in nodes or c not in nodes:
                        continue
                    src, dst = (c, p) if ancestors else (p, c)
                    if src != node:
                        continue
                    pair = (dst, start) if ancestors else (start, dst)
                    if dst in kept:
                        out.setdefault(pair, {"direct": set(), "hops": set()})
                        if node == start:
                            out[pair]["direct"].add(role)
                        else:
                            out[pair]["hops"].add(len(chain) + 1)
                    elif dst not in seen:
                        seen.add(dst)
                        nxt.append((dst, (*chain, role)))
            frontier = nxt
    return kept, out


def reachable(pairs, ancestors):
    """For each node, everything beyond it (away from the root) along `pairs` (parent, child)."""
    beyond = {}
    for p, c in pairs:
        src, dst = (c, p) if ancestors else (p, c)
        beyond.setdefault(src, set()).add(dst)
    closure = {}

    def walk(n):
        if n not in closure:
            closure[n] = set()
            for m in beyond.get(n, ()):
                closure[n] |= {m} | walk(m)
        return closure[n]

    for n in list(beyond):
        walk(n)
    return closure


@pytest.mark.parametrize("ancestors", [True, False])
def test_contracted_edges_match_the_reference_and_keep_ancestry_connected(dag, ancestors):
    cat, ids, kinds, edges = dag
    starts = [ids[-1], ids[-40], ids[200]] if ancestors else [ids[1], ids[35], ids[60]]
    for start in starts:
        rows = (cat.ancestors if ancestors else cat.descendants)(start)
        root = SimpleNamespace(id=start, kind=kinds[start], name="root")
        walked = {r.id for r in rows}
        for kept_kinds in [{"checkpoint", "vector"}, {"checkpoint"}, {"evaluation"}]:
            got = keep_kinds(rows, root, ancestors, kinds=kept_kinds)
            kept, want = reference(edges, kinds, start, walked, ancestors, kept_kinds)
            assert {r.id for r in got} == kept - {start}  # every kept node is still reached
            assert all(r.kind in kept_kinds for r in got)
            links = [link for r in got for link in r.links]
            assert len(links) == len(set(links))
            pairs = {}
            for p, c, role in links:
                pairs.setdefault((p, c), []).append(role)
            assert set(pairs) == set(want)
            for pair, roles in pairs.items():
                if want[pair]["direct"]:
                    assert set(roles) == want[pair]["direct"]
                else:  # one edge: the roles of a shortest hidden path
                    assert len(roles) == 1 and roles[0].count(CHAIN) + 1 == min(want[pair]["hops"])
            # Ancestry among kept nodes is what it was in the full walk.
            full = reachable({(p, c) for p, c, _ in edges if {p, c} <= walked | {start}}, ancestors)
            contracted = reachable(set(pairs), ancestors)
            for node in kept:
                assert contracted.get(node, set()) == full.get(node, set()) & kept, node
            # Depths count kept hops: one more than the nearest kept node a link comes from.
            depth = {start: 0} | {r.id: r.depth for r in got}
            for r in got:
                nearer = [c if ancestors else p for p, c, _ in r.links]
                assert r.depth == 1 + min(depth[n] for n in nearer)
                assert r.path[0] == start and r.path[-1] == r.id and len(r.path) == r.depth + 1


def test_hide_is_the_complement_and_depth_counts_kept_hops(dag):
    cat, ids, kinds, _ = dag
    start = ids[-1]
    rows = cat.ancestors(start)
    root = SimpleNamespace(id=start, kind=kinds[start], name="root")
    shown = keep_kinds(rows, root, True, kinds={"checkpoint", "vector"})
    hidden = keep_kinds(rows, root, True, hide={"evaluation", "selection", "dataset", None})
    assert [r.model_dump() for r in shown] == [r.model_dump() for r in hidden]
    assert max(r.depth for r in shown) > 2
    for d in (1, 2):
        cut = keep_kinds(rows, root, True, kinds={"checkpoint", "vector"}, max_depth=d)
        assert {r.id: r.depth for r in cut} == {r.id: r.depth for r in shown if r.depth <= d}
        kept = {start} | {r.id for r in cut}
        assert all({p, c} <= kept for r in cut for p, c, _ in r.links)
    everything = keep_kinds(rows, root, True, hide=set())  # nothing hidden: the walk as it was
    assert {(r.id, r.depth) for r in everything} == {(r.id, r.depth) for r in rows}
    assert {link for r in everything for link in r.links} == {link for r in rows for link in r.links}


def test_views_draw_the_contracted_edges_coloured_by_kind(dag):
    cat, ids, kinds, _ = dag
    start = ids[-1]
    root = SimpleNamespace(id=start, kind=kinds[start], name="root")
    got = keep_kinds(cat.ancestors(start), root, True, kinds={"checkpoint", "vector"})
    links = {(p[:12], c[:12], role) for r in got for p, c, role in r.links}
    assert any(CHAIN in role for _, _, role in links)
    assert tree_edges(as_tree(got, root), True) == links
    mermaid = as_mermaid(got, root, True)
    assert mermaid_edges(mermaid) == links
    classes = [line.split()[1] for line in mermaid.splitlines() if line.strip().startswith("classDef")]
    assert classes == sorted({"kind_checkpoint", "kind_vector", f"kind_{kinds[start] or 'unknown'}"})
    painted = {
        n
        for line in mermaid.splitlines()
        if line.strip().startswith("class ")
        for n in line.split()[1].split(",")
    }
    assert painted == {f"n{start[:12]}"} | {f"n{r.id[:12]}" for r in got}


def test_cli_kinds_on_a_registered_history_keeps_names_escaped(tmp_path):
    """θ_ft → γ → θ_meta → downstream → evaluation → report: `--kinds checkpoint` links θ_ft to θ_meta
    through γ, and a hostile name is escaped as before."""
    api = ArtifactsAPI(str(tmp_path / "home"))
    pt = api.register_json({"w": 0}, "checkpoint", 'θ_pt "x" |y| <b>').id
    ft = api.register_json({"w": 1}, "checkpoint", "θ_ft", parents=[(pt, "init")]).id
    gamma = api.register_json({"g": 1}, "vector", "γ", parents=[(ft, "subtrahend"), (pt, "base")]).id
    meta = api.register_json({"m": 1}, "checkpoint", "θ_meta", parents=[(gamma, "vector")]).id
    down = api.register_json({"d": 1}, "checkpoint", "downstream", parents=[(meta, "init")]).id
    doc = {"checkpoint_id": down, "fingerprint": "f" * 64, "episodes": []}
    evaluation = api.register_evaluation(doc, "evaluate downstream").id
    report = api.register_json({"r": 1}, "report", "report", parents=[(evaluation, "evaluation")]).id

    def lineage(*args):
        result = CliRunner().invoke(app, ["--home", str(tmp_path / "home"), "lineage", *args])
        assert result.exit_code == 0, (result.output, result.exception)
        return result.stdout

    tree = lineage(report, "--kinds", "checkpoint")
    assert tree_edges(tree, True) == {
        (down[:12], report[:12], f"checkpoint{CHAIN}evaluation"),
        (meta[:12], down[:12], "init"),
        (ft[:12], meta[:12], f"subtrahend{CHAIN}vector"),
        (pt[:12], meta[:12], f"base{CHAIN}vector"),
        (pt[:12], ft[:12], "init"),
    }
    assert "γ" not in tree and "evaluate" not in tree
    assert tree_edges(lineage(report, "--hide", "vector,evaluation"), True) == tree_edges(tree, True)
    assert tree_edges(lineage(report, "--kinds", "checkpoint", "--depth", "2"), True) == {
        (down[:12], report[:12], f"checkpoint{CHAIN}evaluation"),
        (meta[:12], down[:12], "init"),
    }
    mermaid = lineage(report, "--kinds", "checkpoint,vector", "--format", "mermaid")
    assert "#quot;x#quot; #124;y#124; #lt;b#gt;" in mermaid and "<b>" not in mermaid
    assert "classDef kind_vector" in mermaid and "classDef kind_evaluation" not in mermaid
    assert (gamma[:12], meta[:12], "vector") in mermaid_edges(mermaid)
    descendants = lineage(pt, "--descendants", "--kinds", "checkpoint,report")
    assert (down[:12], report[:12], f"checkpoint{CHAIN}evaluation") in tree_edges(descendants, False)


def study_history(path, runs=12, snapshots=4, evaluations=3):
    """A study's history as the flows register it: θ_pt from the demos; per run, its snapshots and its
    final checkpoint from θ_pt and the demos, each evaluated `evaluations` times, and every evaluation
    a parent of the study: 44 edges a run, 529 in all."""
    ids, edges = {}, []

    def add(kind, name, *parents):
        ids[name] = hashlib.sha256(name.encode()).hexdigest()
        edges.extend((ids[parent], ids[name], role) for parent, role in parents)
        return name, kind

    named = [add("dataset", "demos"), add("checkpoint", "θ_pt", ("demos", "data"))]
    for run in range(runs):
        points = [f"run {run} @ {10 * (s + 1)} steps" for s in range(snapshots)]
        named += [add("checkpoint", p, ("demos", "data"), ("θ_pt", "init")) for p in points]
        starts = [("demos", "data"), ("θ_pt", "init")]
        named.append(add("checkpoint", f"run {run}", *starts, *((p, "snapshot") for p in points)))
        for checkpoint in [*points, f"run {run}"]:
            named += [
                add("evaluation", f"evaluate {checkpoint} #{e}", (checkpoint, "checkpoint"))
                for e in range(evaluations)
            ]
    tested = [(name, "test") for name, kind in named if kind == "evaluation"]
    named.append(add("study", "analyse study s", *tested))
    cat = Catalogue(path / "catalogue.duckdb")
    con = duckdb.connect(str(cat.path))
    con.execute(  # one statement: a row at a time costs seconds
        "INSERT INTO artifacts (id, kind, name, layout, size_bytes, n_files) "
        "SELECT unnest($1), unnest($2), unnest($3), 'file', 1, 1",
        [[ids[name] for name, _ in named], [kind for _, kind in named], [name for name, _ in named]],
    )
    con.execute(
        "INSERT INTO edges (parent, child, role) SELECT unnest($1), unnest($2), unnest($3)",
        [[edge[i] for edge in edges] for i in range(3)],
    )
    con.close()
    return cat, ids


def drawn(mermaid):
    """The edges and the node labels of a Mermaid graph, its `%%` comments left aside."""
    lines = [line for line in mermaid.splitlines() if not line.strip().startswith("%%")]
    return mermaid_edges("\n".join(lines)), dict(re.findall(r'n([0-9a-f]{12})\["([^"]*)"\]', mermaid))


def test_a_mermaid_lineage_over_500_edges_is_contracted_until_it_fits_with_a_note(tmp_path):
    """Mermaid draws nothing past 500 edges (its default `maxEdges`): a bigger lineage is drawn with
    each run's snapshots and each checkpoint's evaluations as one node, then (to fit a smaller limit)
    every evaluation as one node, then every kind as one node; a note says what and how to see it whole."""
    cat, ids = study_history(tmp_path)
    study = ids["analyse study s"]
    rows = cat.ancestors(study)
    root = SimpleNamespace(id=study, kind="study", name="analyse study s")
    whole, note = mermaid_lineage(rows, root, True, max_edges=10_000)
    assert note is None and len(drawn(whole)[0]) == 529
    graph, note = mermaid_lineage(rows, root, True)
    assert as_mermaid(rows, root, True) == graph
    assert graph.splitlines()[1] == "    %% " + note.removeprefix("> ").replace("**", "")
    edges, labels = drawn(graph)
    assert note.startswith("> **Lineage contracted:** its 529 edges are over Mermaid's limit of 500")
    assert f"({len(edges)} edges drawn)" in note and f"`capvector lineage {study[:12]} --format json`" in note
    assert "snapshots of each run and the evaluations of each checkpoint" in note and "--depth" in note
    assert len(edges) <= 500
    for run in range(12):
        final = ids[f"run {run}"][:12]
        snaps = f"4 snapshots of checkpoint run {run} [{final}]"
        group = {v: k for k, v in labels.items()}
        assert labels[final] == f"checkpoint run {run} [{final}]"
        assert (group[snaps], final, "snapshot") in edges
        assert (group[f"3 evaluations of checkpoint run {run} [{final}]"], study[:12], "test") in edges
        assert (group[snaps], group[f"12 evaluations of {snaps}"], "checkpoint") in edges
    assert not any(ids["run 0 @ 10 steps"][:12] == k or "evaluate" in v for k, v in labels.items())

    edges, labels = drawn(mermaid_lineage(rows, root, True, max_edges=100)[0])
    assert len(edges) <= 100 and "evaluation ×180" in labels.values()
    assert {f"checkpoint run {r} [{ids[f'run {r}'][:12]}]" for r in range(12)} <= set(labels.values())
    graph, note = mermaid_lineage(rows, root, True, max_edges=8)
    edges, labels = drawn(graph)
    assert "every kind is drawn as one node" in note and len(edges) <= 8
    assert sorted(labels.values()) == sorted(
        [
            f"study analyse study s [{study[:12]}]",
            "checkpoint ×61",
            "evaluation ×180",
            f"dataset demos [{ids['demos'][:12]}]",
        ]
    )
    pretrained = SimpleNamespace(id=ids["θ_pt"], kind="checkpoint", name="θ_pt")
    down, note = mermaid_lineage(cat.descendants(ids["θ_pt"]), pretrained, False, max_edges=100)
    assert down.startswith("graph TD") and f"{ids['θ_pt'][:12]} --descendants --format json" in note


def test_the_cli_prints_a_contracted_graph_on_stdout_and_the_note_on_stderr(tmp_path, monkeypatch):
    api = ArtifactsAPI(str(tmp_path / "home"))
    pt = api.register_json({"w": 0}, "checkpoint", "θ_pt").id
    ft = api.register_json({"w": 1}, "checkpoint", "θ_ft", parents=[(pt, "init")]).id
    evaluations = [
        api.register_evaluation({"checkpoint_id": ft, "fingerprint": f"{i}" * 64, "episodes": []}, f"e{i}").id
        for i in range(3)
    ]
    report = api.register_json(
        {"r": 1}, "report", "report", parents=[(e, "evaluation") for e in evaluations]
    ).id
    limited = functools.partial(mermaid_lineage, max_edges=4)  # 7 edges: the 3 evaluations as one
    monkeypatch.setattr(inspect_commands, "mermaid_lineage", limited)
    result = CliRunner().invoke(
        app, ["--home", str(tmp_path / "home"), "lineage", report, "--format", "mermaid"]
    )
    assert result.exit_code == 0, (result.output, result.exception)
    edges, labels = drawn(result.stdout)
    assert len(edges) == 3 and f"3 evaluations of checkpoint θ_ft [{ft[:12]}]" in labels.values()
    assert result.stderr.startswith("> **Lineage contracted:** its 7 edges are over Mermaid's limit of 4")
