"""Lineage rows rendered for people: an indented tree, or a Mermaid graph for Markdown viewers.

History is a DAG (θ_pt is a parent of θ_ft, θ_ao and θ_meta), so both views draw every edge among the
rows: the rows' `links` (capvector.artifacts.catalogue.LineageNode); rows without them fall back to the hop
each row was first reached by. The tree shows each node in full once, under the node it is nearest the root
through, and every other edge into it as a one-line reference marked ↑ (shown above) or ↓ (below).

At study size a lineage has hundreds of nodes; `keep_kinds` keeps some kinds (checkpoints and vectors,
say) and contracts the edges through the others, so what is kept stays connected as it was. Mermaid
draws nothing past 500 edges: `mermaid_lineage` groups repeats (a run's snapshots, a checkpoint's
evaluations), then kinds, until the graph fits, and says so.
"""

from __future__ import annotations

import hashlib
import re
import unicodedata
from collections import deque
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field
from typing import Any

from capvector.artifacts.records import ArtifactRecord, LineageRow

# Mermaid entity codes: `"` would end a quoted label, `|` an edge label, `#` starts an entity code, `<`
# and `>` would be read as HTML, a backtick as a Markdown string.
_MERMAID_ESCAPES = {"#": "#35;", '"': "#quot;", "|": "#124;", "<": "#lt;", ">": "#gt;", "`": "#96;"}


_C_ESCAPES = {"\n": "\\n", "\r": "\\r", "\t": "\\t"}


def single_line(text: str) -> str:
    """`text` as one printable line: control, format and line-separator characters written as escapes
    (`\\n`, `\\x1b`, `\\u202e`). Registration refuses them; a record written before that may hold them,
    and a newline in a name would otherwise draw a forged lineage line."""
    out = []
    for c in text:
        if unicodedata.category(c) in ("Cc", "Cf", "Zl", "Zp"):
            out.append(_C_ESCAPES.get(c) or (f"\\x{ord(c):02x}" if ord(c) < 0x100 else f"\\u{ord(c):04x}"))
        else:
            out.append(c)
    return "".join(out)


def _label(row_id: str, kind: str | None, name: str | None) -> str:
    return single_line(f"{kind or '?'} {name or ''} [{row_id[:12]}]".strip())


def mermaid_text(text: str) -> str:
    """`text` made safe inside a quoted Mermaid label or an edge label (one line, entity codes)."""
    return "".join(_MERMAID_ESCAPES.get(c, c) for c in single_line(text))


def lineage_edges(rows: Sequence[LineageRow], root_id: str) -> list[tuple[str, str, str, str]]:
    """(near, far, role, parent) for every edge among the rows, once each: `far` is the row the edge
    belongs to, `near` its other end (towards the root along the walk), `parent` the edge's parent
    ("" for a fallback hop, whose direction the caller knows)."""
    out, seen = [], set()
    for row in rows:
        if row.depth == 0:
            continue
        links = getattr(row, "links", None)
        if links:
            for parent, child, role in links:
                key = (parent, child, role)
                if key not in seen:
                    seen.add(key)
                    out.append((child if parent == row.id else parent, row.id, role, parent))
        else:  # a row without links: the hop it was first reached by
            near = row.path[-2] if len(row.path) > 1 else root_id
            out.append((near, row.id, row.roles[-1], ""))
    return out


EdgeNotes = dict[tuple[str, str, str], str]
"""(parent, child, role) -> what an edge's label adds to its role (a merge's `α=0.5` on its vector edge)."""


def edge_notes(api: Any, ids: Sequence[str]) -> EdgeNotes:
    """The α of every `vector` edge into one of `ids` whose record carries one (merges record it)."""
    if not ids:
        return {}
    _, found = api.query_rows(
        "SELECT parent, child, role, TRY_CAST(attrs->>'alpha' AS DOUBLE) FROM edges "
        "WHERE role = 'vector' AND child IN (SELECT UNNEST($ids)) AND attrs->>'alpha' IS NOT NULL",
        {"ids": list(ids)},
    )
    return {(p, c, r): f"α={alpha:g}" for p, c, r, alpha in found if alpha is not None}


def _edge_label(role: str, parent: str, child: str, notes: EdgeNotes) -> str:
    note = notes.get((parent, child, role))
    return f"{role} {note}" if note else role


def as_tree(rows: list[LineageRow], root: ArtifactRecord, notes: EdgeNotes | None = None) -> str:
    """Each node in full under the node it was first reached from, every other edge as a reference;
    an edge's role with its note (`notes`, e.g. a merge's α) when it has one."""
    by_id = {r.id: r for r in rows}
    kids: dict[str, list[tuple[str, str]]] = {}
    for near, far, role, parent in lineage_edges(rows, root.id):
        if notes and parent:
            role = _edge_label(role, parent, near if parent == far else far, notes)
        kids.setdefault(near, []).append((far, role))
    for items in kids.values():
        items.sort(
            key=lambda k: (by_id[k[0]].depth, k[1], by_id[k[0]].kind or "", by_id[k[0]].name or "", k[0])
        )

    def home_of(row: LineageRow) -> str:
        """The node a row is shown in full under: the hop of its first (shortest) path."""
        return row.path[-2] if len(row.path) > 1 else root.id

    lines = [_label(root.id, root.kind, root.name)]
    shown = {root.id}

    def walk(node: str, indent: str) -> None:
        items = kids.get(node, [])
        for i, (far, role) in enumerate(items):
            last = i == len(items) - 1
            row = by_id[far]
            label = f"({single_line(role)}) {_label(far, row.kind, row.name)}"
            branch = "└── " if last else "├── "
            if home_of(row) == node and far not in shown:
                shown.add(far)
                lines.append(f"{indent}{branch}{label}")
                walk(far, indent + ("    " if last else "│   "))
            else:
                lines.append(f"{indent}{branch}{label} {'↑' if far in shown else '↓'}")

    walk(root.id, "")
    return "\n".join(lines)


# A contracted edge's role: the roles along the hidden path, from parent to child.
CHAIN = " → "


def keep_kinds(
    rows: Sequence[LineageRow],
    root: ArtifactRecord,
    ancestors: bool,
    kinds: Collection[str] | None = None,
    hide: Collection[str] | None = None,
    max_depth: int | None = None,
) -> list[LineageRow]:
    """The rows of the kinds kept (`kinds`: only these, if given; `hide`: not these; the root always),
    with every path through the others contracted into one edge, so ancestry stays connected.

    A kept node is linked to each nearest kept node beyond it (away from the root): by its direct
    edges when there are any, else by one edge whose role is the roles of the shortest hidden path
    joined by CHAIN (parent to child). Depths and paths count kept hops, and `max_depth` applies to
    them (walk the full lineage first: a depth in the walk counts hidden hops too). Rows of an
    artifact without a catalogue row (kind None) are hidden by `kinds` and kept by `hide`."""

    def visible(kind: str | None) -> bool:
        return (kinds is None or kind in kinds) and (hide is None or kind not in hide)

    by_id = {r.id: r for r in rows}
    kept = {root.id} | {r.id for r in rows if visible(r.kind)}
    away: dict[str, list[tuple[str, str]]] = {}  # node -> (next node away from the root, role)
    for near, far, role, parent in lineage_edges(rows, root.id):
        if not parent:  # fallback hop: parent by direction
            parent = far if ancestors else near
        child = near if parent == far else far
        src, dst = (child, parent) if ancestors else (parent, child)
        away.setdefault(src, []).append((dst, role))
    for items in away.values():
        items.sort()

    edges: dict[tuple[str, str], list[str]] = {}  # (near, far) in kept nodes -> roles
    for start in sorted(kept):
        direct: dict[str, list[str]] = {}
        via: dict[str, tuple[str, ...]] = {}
        queue, seen = deque([(start, ())]), {start}
        while queue:  # breadth first through hidden nodes: the first path found is a shortest
            node, chain = queue.popleft()
            for nxt, role in away.get(node, []):
                if nxt in kept:
                    if node == start:
                        direct.setdefault(nxt, []).append(role)
                    else:
                        via.setdefault(nxt, (*chain, role))
                elif nxt not in seen:
                    seen.add(nxt)
                    queue.append((nxt, (*chain, role)))
        for far in sorted(set(direct) | set(via)):
            chain = via.get(far, ())
            edges[start, far] = direct.get(far) or [CHAIN.join(reversed(chain) if ancestors else chain)]

    # Depths and paths over the kept graph: breadth first from the root, each node's path extending
    # that of its smallest (near end, role) edge from the level before, as the catalogue's walk does.
    beyond: dict[str, list[tuple[str, list[str]]]] = {}
    for (near, far), roles in edges.items():
        beyond.setdefault(near, []).append((far, roles))
    depth, paths = {root.id: 0}, {root.id: ([root.id], [])}
    frontier = [root.id]
    while frontier and (max_depth is None or depth[frontier[0]] < max_depth):
        hops: dict[str, tuple[str, str]] = {}
        for near in frontier:
            for far, roles in beyond.get(near, []):
                if far not in depth:
                    hops[far] = min(hops.get(far, (near, min(roles))), (near, min(roles)))
        for far, (near, role) in hops.items():
            depth[far] = depth[near] + 1
            ids, path_roles = paths[near]
            paths[far] = ([*ids, far], [*path_roles, role])
        frontier = sorted(hops)
    links: dict[str, list[tuple[str, str, str]]] = {}  # a row's links: its edges towards the root
    for (near, far), roles in edges.items():
        if near in depth and far in depth:
            links.setdefault(far, []).extend((far, near, r) if ancestors else (near, far, r) for r in roles)
    out = []
    for node in sorted((n for n in depth if n != root.id), key=lambda n: (depth[n], n)):
        ids, path_roles = paths[node]
        update = {"depth": depth[node], "path": ids, "roles": path_roles, "links": links.get(node, [])}
        out.append(by_id[node].model_copy(update=update))
    return out


# Fill colours of the kinds the project registers; any other kind gets one from FALLBACK_FILLS.
KIND_FILLS = {
    "checkpoint": "#cfe2ff",
    "vector": "#ffe08a",
    "dataset": "#d1f2d9",
    "evaluation": "#eadcff",
    "report": "#ffd6d6",
    "vector_stats": "#fff4c2",
    "selection": "#d9f3f7",
    "adapter": "#e6e6e6",
}
FALLBACK_FILLS = ("#f8d7ee", "#dff0c8", "#fde2c8", "#d6e4f0", "#ece0d1")


def _kind_class(kind: str | None) -> str:
    """A Mermaid class name for a kind: its letters, digits and underscores, plus a hash of the kind
    when it has any other character (so two kinds never share a class)."""
    if kind is None:
        return "kind_unknown"
    safe = re.sub(r"[^A-Za-z0-9_]", "_", kind)
    if safe != kind:
        safe += "_" + hashlib.sha256(kind.encode()).hexdigest()[:8]
    return f"kind_{safe}"


def _kind_fill(kind: str | None) -> str:
    if kind in KIND_FILLS:
        return KIND_FILLS[kind]
    digest = hashlib.sha256((kind or "").encode()).digest()
    return FALLBACK_FILLS[digest[0] % len(FALLBACK_FILLS)]


MERMAID_MAX_EDGES = 500
"""Mermaid's default `maxEdges`: a graph with more edges is not drawn at all (an error in its place)."""


@dataclass
class MermaidGraph:
    """What a Mermaid view draws: each node's label and kind, how many artifacts a node stands for
    (`sizes`: a group's members; 1 when absent), and the edges (parent, child, role, label) in order."""

    labels: dict[str, str]
    kinds: dict[str, str | None]
    edges: list[tuple[str, str, str, str]]
    sizes: dict[str, int] = field(default_factory=dict)

    def label(self, node: str) -> str:
        return self.labels.get(node, node[:12])

    def count(self, nodes: Sequence[str]) -> int:
        return sum(self.sizes.get(n, 1) for n in nodes)


def _mermaid_graph(
    rows: list[LineageRow], root: ArtifactRecord, ancestors: bool, notes: EdgeNotes | None = None
) -> MermaidGraph:
    """Every edge among the rows, parent to child, labelled with its role and its note."""
    labels = {r.id: _label(r.id, r.kind, r.name) for r in rows}
    labels[root.id] = _label(root.id, root.kind, root.name)
    edges = []
    for near, far, role, parent in lineage_edges(rows, root.id):
        if not parent:  # fallback hop: parent by direction
            parent = far if ancestors else near
        child = near if parent == far else far
        edges.append((parent, child, role, _edge_label(role, parent, child, notes or {})))
    return MermaidGraph(labels, {r.id: r.kind for r in rows} | {root.id: root.kind}, edges)


def _merged(
    graph: MermaidGraph, groups: list[tuple[str, str | None, list[str]]], join_roles: bool = False
) -> MermaidGraph:
    """`graph` with the members of each group (label, kind, members) drawn as one node: an edge into
    or out of a group drawn once per label, or once per pair of nodes with its labels joined."""
    labels, kinds, sizes, into = dict(graph.labels), dict(graph.kinds), dict(graph.sizes), {}
    for label, kind, members in groups:
        group = hashlib.sha256("\n".join(sorted(members)).encode()).hexdigest()
        labels[group], kinds[group], sizes[group] = label, kind, graph.count(members)
        for member in members:
            into[member] = group
            for found in (labels, kinds, sizes):
                found.pop(member, None)
    merged: dict[tuple[str, str, str], list[str]] = {}
    for parent, child, role, label in graph.edges:
        parent, child = into.get(parent, parent), into.get(child, child)
        if parent == child:
            continue
        said = merged.setdefault((parent, child, "" if join_roles else role), [])
        if label not in said:
            said.append(label)
    edges = []
    for (parent, child, role), said in merged.items():
        if join_roles:
            edges.append((parent, child, ", ".join(said), ", ".join(said)))
        else:
            edges.extend((parent, child, role, label) for label in said)
    return MermaidGraph(labels, kinds, edges, sizes)


def _members(group_of: dict[str, Any]) -> dict[Any, list[str]]:
    """{group: its nodes} of {node: its group}, groups of one node left out (nothing to contract)."""
    out: dict[Any, list[str]] = {}
    for node, group in group_of.items():
        out.setdefault(group, []).append(node)
    return {group: nodes for group, nodes in out.items() if len(nodes) > 1}


def _repeats_per_checkpoint(graph: MermaidGraph, root_id: str) -> MermaidGraph:
    """The snapshots of each run as one node, then the evaluations of each checkpoint (or of a run's
    snapshots, now one node) as one node."""
    run_of: dict[str, str] = {}
    for parent, child, role, _ in graph.edges:
        if role == "snapshot" and parent != root_id:
            run_of.setdefault(parent, child)
    graph = _merged(
        graph,
        [
            (f"{graph.count(m)} snapshots of {graph.label(run)}", "checkpoint", m)
            for run, m in _members(run_of).items()
        ],
    )
    checkpoint_of: dict[str, str] = {}
    for parent, child, role, _ in graph.edges:
        if role == "checkpoint" and graph.kinds.get(child) == "evaluation" and child != root_id:
            checkpoint_of.setdefault(child, parent)
    return _merged(
        graph,
        [
            (f"{graph.count(m)} evaluations of {graph.label(checkpoint)}", "evaluation", m)
            for checkpoint, m in _members(checkpoint_of).items()
        ],
    )


def _by_kind(
    graph: MermaidGraph, root_id: str, keep: Collection[str] = (), join_roles: bool = False
) -> MermaidGraph:
    """Every node but the root's and those of the kinds in `keep` drawn as one node per kind."""
    kind_of = {
        node: graph.kinds.get(node)
        for edge in graph.edges
        for node in edge[:2]
        if node != root_id and graph.kinds.get(node) not in keep
    }
    groups = [(f"{kind or '?'} ×{graph.count(m)}", kind, m) for kind, m in _members(kind_of).items()]
    return _merged(graph, groups, join_roles)


# How a graph over MERMAID_MAX_EDGES is contracted: one step more at a time until it fits (each step
# after the first also does what the steps before it did).
CONTRACTIONS = (
    ("the snapshots of each run and the evaluations of each checkpoint are drawn as one node each",
     _repeats_per_checkpoint),
    ("the snapshots of each run and the evaluations of each checkpoint are drawn as one node each, and "
     "the artifacts of every kind but checkpoint and vector as one node per kind",
     lambda graph, root_id: _by_kind(graph, root_id, keep=("checkpoint", "vector"))),
    ("every kind is drawn as one node (the root apart), with one edge per pair of them, its roles joined",
     lambda graph, root_id: _by_kind(graph, root_id, join_roles=True)),
)  # fmt: skip


def _contracted(graph: MermaidGraph, root_id: str, max_edges: int) -> tuple[MermaidGraph, str | None]:
    """`graph` contracted (CONTRACTIONS) until it has at most `max_edges` edges, and what was done
    (None when it fitted as it was)."""
    done = None
    for what, contract in CONTRACTIONS:
        if len(graph.edges) <= max_edges:
            break
        graph, done = contract(graph, root_id), what
    return graph, done


def _contraction_note(
    what: str, edges: tuple[int, int], max_edges: int, root: ArtifactRecord, ancestors: bool
) -> str:
    """One Markdown line: why the graph is not whole, what was grouped, and how to see it whole."""
    command = f"capvector lineage {root.id[:12]}{'' if ancestors else ' --descendants'} --format json"
    return (
        f"> **Lineage contracted:** its {edges[0]} edges are over Mermaid's limit of {max_edges} "
        f"(`maxEdges`), so {what} ({edges[1]} edges drawn). See it whole with "
        f"`{command}`, or draw less of it with `--depth N` or `--kinds checkpoint,vector`."
    )


def _draw(graph: MermaidGraph, root_id: str, ancestors: bool, comment: str | None = None) -> str:
    """The Mermaid text: edges, a `classDef` per kind and the nodes of each, `comment` as a `%%` line."""

    def node(artifact_id: str) -> str:
        return f'n{artifact_id[:12]}["{mermaid_text(graph.label(artifact_id))}"]'

    lines = [
        f"    {node(parent)} -->|{mermaid_text(label)}| {node(child)}"
        for parent, child, _, label in graph.edges
    ]
    lines = lines or [f"    {node(root_id)}"]
    drawn = {m for line in lines for m in re.findall(r"\bn([0-9a-f]{12})\[", line)}
    by_class: dict[str, tuple[str | None, list[str]]] = {}
    for artifact_id, kind in sorted(graph.kinds.items(), key=lambda kv: kv[0]):
        if artifact_id[:12] in drawn:
            by_class.setdefault(_kind_class(kind), (kind, []))[1].append(f"n{artifact_id[:12]}")
    for cls, (kind, nodes) in sorted(by_class.items()):
        lines.append(f"    classDef {cls} fill:{_kind_fill(kind)},stroke:#555")
        lines.append(f"    class {','.join(nodes)} {cls}")
    head = ["graph " + ("BT" if ancestors else "TD"), *([f"    %% {comment}"] if comment else [])]
    return "\n".join(head + lines)


def mermaid_lineage(
    rows: list[LineageRow],
    root: ArtifactRecord,
    ancestors: bool,
    notes: EdgeNotes | None = None,
    max_edges: int = MERMAID_MAX_EDGES,
) -> tuple[str, str | None]:
    """The Mermaid graph (see `as_mermaid`) and, when it had more than `max_edges` edges and was
    contracted to fit (Mermaid draws nothing past its limit), a Markdown note saying so (also in the
    graph, as a `%%` comment); None when it is whole."""
    graph = _mermaid_graph(rows, root, ancestors, notes)
    drawn, what = _contracted(graph, root.id, max_edges)
    if what is None:
        return _draw(graph, root.id, ancestors), None
    note = _contraction_note(what, (len(graph.edges), len(drawn.edges)), max_edges, root, ancestors)
    return _draw(drawn, root.id, ancestors, note.removeprefix("> ").replace("**", "")), note


def as_mermaid(
    rows: list[LineageRow], root: ArtifactRecord, ancestors: bool, notes: EdgeNotes | None = None
) -> str:
    """`graph BT` for ancestors (arrows point from parent to child), `graph TD` for descendants; nodes
    are coloured by kind (a `classDef` per kind, then the nodes of each); an edge's label is its role
    with its note (`notes`, e.g. a merge's α) when it has one. Over MERMAID_MAX_EDGES edges, contracted
    (`mermaid_lineage`)."""
    return mermaid_lineage(rows, root, ancestors, notes)[0]
