"""Lineage rows rendered for people: an indented tree, or a Mermaid graph for Markdown viewers."""

from __future__ import annotations

from artifacts.records import ArtifactRecord, LineageRow


def _label(row_id: str, kind: str | None, name: str | None) -> str:
    return f"{kind or '?'} {name or ''} [{row_id[:12]}]".strip()


def as_tree(rows: list[LineageRow], root: ArtifactRecord) -> str:
    """Each node under the node it was reached from (first path), with the edge role."""
    children: dict[str, list[LineageRow]] = {}
    for row in rows:
        if row.depth == 0:
            continue
        children.setdefault(row.path[-2], []).append(row)
    root_id = root.id
    lines = [_label(root_id, root.kind, root.name)]

    def walk(node: str, indent: str) -> None:
        kids = children.get(node, [])
        for i, kid in enumerate(kids):
            last = i == len(kids) - 1
            lines.append(
                f"{indent}{'└── ' if last else '├── '}({kid.roles[-1]}) {_label(kid.id, kid.kind, kid.name)}"
            )
            walk(kid.id, indent + ("    " if last else "│   "))

    walk(root_id, "")
    return "\n".join(lines)


def as_mermaid(rows: list[LineageRow], root: ArtifactRecord, ancestors: bool) -> str:
    """`graph BT` for ancestors (arrows point from parent to child), `graph TD` for descendants."""
    lines = ["graph " + ("BT" if ancestors else "TD")]
    root_id = root.id
    names = {r.id: _label(r.id, r.kind, r.name) for r in rows}
    names[root_id] = _label(root_id, root.kind, root.name)
    seen = set()
    for row in rows:
        if row.depth == 0:
            continue
        near, far = row.path[-2], row.id
        parent, child = (far, near) if ancestors else (near, far)
        edge = (parent, child, row.roles[-1])
        if edge in seen:
            continue
        seen.add(edge)
        lines.append(
            f'    n{parent[:12]}["{names.get(parent, parent[:12])}"] -->|{row.roles[-1]}| '
            f'n{child[:12]}["{names.get(child, child[:12])}"]'
        )
    if len(lines) == 1:
        lines.append(f'    n{root_id[:12]}["{names[root_id]}"]')
    return "\n".join(lines)
