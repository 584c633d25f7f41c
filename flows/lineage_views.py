"""Lineage rows rendered for people: an indented tree, or a Mermaid graph for Markdown viewers.

History is a DAG (θ_pt is a parent of θ_ft, θ_ao and θ_meta), so both views draw every edge among the
rows: the rows' `links` (artifacts.catalogue.LineageNode); rows without them fall back to the hop each
row was first reached by. The tree shows each node in full once, under the node it is nearest the root
through, and every other edge into it as a one-line reference marked ↑ (shown above) or ↓ (below).
"""

from __future__ import annotations

import unicodedata
from collections.abc import Sequence

from artifacts.records import ArtifactRecord, LineageRow

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


def as_tree(rows: list[LineageRow], root: ArtifactRecord) -> str:
    """Each node in full under the node it was first reached from, every other edge as a reference."""
    by_id = {r.id: r for r in rows}
    kids: dict[str, list[tuple[str, str]]] = {}
    for near, far, role, _ in lineage_edges(rows, root.id):
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


def as_mermaid(rows: list[LineageRow], root: ArtifactRecord, ancestors: bool) -> str:
    """`graph BT` for ancestors (arrows point from parent to child), `graph TD` for descendants."""
    lines = ["graph " + ("BT" if ancestors else "TD")]
    names = {r.id: _label(r.id, r.kind, r.name) for r in rows}
    names[root.id] = _label(root.id, root.kind, root.name)

    def node(artifact_id: str) -> str:
        return f'n{artifact_id[:12]}["{mermaid_text(names.get(artifact_id, artifact_id[:12]))}"]'

    for near, far, role, parent in lineage_edges(rows, root.id):
        if not parent:  # fallback hop: parent by direction
            parent = far if ancestors else near
        child = near if parent == far else far
        lines.append(f"    {node(parent)} -->|{mermaid_text(role)}| {node(child)}")
    if len(lines) == 1:
        lines.append(f"    {node(root.id)}")
    return "\n".join(lines)
