"""`capvector studies`: the studies of a home, one row each, and two of them side by side.

What `dvc exp show` and MLflow's compare view give for runs, for study reports: the design (draws,
seeds, tasks, goals, endpoint), the preconditions with their verdicts, and every paired comparison at
the primary endpoint, as difference [interval]. A study is a `study` artifact (the analysis step's
document, `capvector.tasks.steps.study_analysis.StudyReport`) in this home, or that document as a JSON
file (`capvector artifacts get ID -o FILE`, e.g. from another home). Read as plain JSON: answering needs
neither pandas nor torch.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from capvector.tasks.runtime.workspace import Workspace

ENDPOINT = -1  # capvector.stats.paired_differences.ENDPOINT (not imported: it loads pandas); a test ties them
STUDY_KIND = "study"


class StudyRow(BaseModel):
    id: str
    name: str
    stage: str
    created_at: str
    code_version: str | None
    draws: int
    seeds: int
    tasks: int
    goals_per_task: int
    gate: str
    headline: str


def _endpoint(doc: dict[str, Any], arm: str, baseline: str) -> dict[str, Any] | None:
    return next(
        (
            c
            for c in doc.get("comparisons", [])
            if (c["arm"], c["baseline"], c["budget"]) == (arm, baseline, ENDPOINT)
        ),
        None,
    )


def difference_cell(c: dict[str, Any] | None) -> str:
    """`+4.8 [+1.2, +8.4]` (points, the interval the report reads), or `–` where not compared."""
    if c is None:
        return "–"
    return f"{c['difference']:+.1f} [{c['ci_low']:+.1f}, {c['ci_high']:+.1f}]"


def _headline(doc: dict[str, Any]) -> str:
    """The primary comparison where the arms ran (θ_meta, then CapVector, vs SFT), else (c′)."""
    for arm, baseline in (("meta_sft", "sft"), ("capvector", "sft"), ("sft_from_ao", "sft")):
        c = _endpoint(doc, arm, baseline)
        if c is not None:
            return f"{arm} − {baseline} {difference_cell(c)}"
    return "–"


def _gate(doc: dict[str, Any]) -> str:
    if doc.get("gate"):
        return "failed"
    return "passed" if doc["design"].get("gate", True) else "not used"


def load_study_doc(workspace: Workspace, ref: str) -> tuple[str, dict[str, Any]]:
    """(id or file name, document) of a study artifact id (a prefix is enough) or a study JSON file."""
    path = Path(ref)
    if path.suffix == ".json" and path.is_file():
        doc = json.loads(path.read_text())
        label = path.name
    else:
        record = workspace.api.get(ref)
        if record.kind != STUDY_KIND:
            raise ValueError(
                f"{ref!r} is a {record.kind!r} artifact, not a study (capvector studies lists them)"
            )
        doc, label = workspace.api.store.open_json(record.id), record.id
    if not isinstance(doc, dict) or "design" not in doc or "comparisons" not in doc:
        raise ValueError(f"{ref!r} is not a study report (no 'design' and 'comparisons')")
    return label, doc


def list_studies(workspace: Workspace) -> list[StudyRow]:
    """Every study artifact of the home, oldest first (a gated study has a gate and a final one)."""
    ids = workspace.api.query_rows(
        "SELECT id, created_at, code_version FROM artifacts WHERE kind = ? ORDER BY created_at, id",
        [STUDY_KIND],
    )[1]
    rows = []
    for artifact_id, created_at, code_version in ids:
        doc = workspace.api.store.open_json(artifact_id)
        design = doc["design"]
        rows.append(
            StudyRow(
                id=artifact_id,
                name=design["name"],
                stage=design.get("stage", "final"),
                created_at=str(created_at)[:19],
                code_version=code_version,
                draws=len(design["draws"]),
                seeds=len(design["seeds"]),
                tasks=len(doc.get("tasks", [])),
                goals_per_task=doc.get("goals_per_task", 0),
                gate=_gate(doc),
                headline=_headline(doc),
            )
        )
    return rows


def _design_rows(a: dict[str, Any], b: dict[str, Any]) -> list[tuple[str, str, str]]:
    def described(doc: dict[str, Any]) -> dict[str, str]:
        d = doc["design"]
        return {
            "study": d["name"],
            "stage": d.get("stage", "final"),
            "draws × seeds": f"{len(d['draws'])} × {len(d['seeds'])}"
            + (f" (replicates of {d['draws_per_replicate']})" if d.get("draws_per_replicate", 1) > 1 else ""),
            "tasks × goals": f"{len(doc.get('tasks', []))} × {doc.get('goals_per_task', 0)}",
            "endpoint budgets": ", ".join(str(x) for x in d["endpoint_budgets"]),
            "arms": ", ".join(d["arms"]),
            "chosen": "; ".join(f"{k} {v:g}" for k, v in d.get("chosen", {}).items()) or "–",
            "gate": _gate(doc),
        }

    left, right = described(a), described(b)
    return [(k, left[k], right[k]) for k in left]


def _precondition_rows(a: dict[str, Any], b: dict[str, Any]) -> list[tuple[str, str, str]]:
    def verdicts(doc: dict[str, Any]) -> dict[str, str]:
        out = {}
        for p in doc.get("preconditions", []):
            holds = {True: "holds", False: "fails", None: "not shown"}[p["holds"]]
            holds = holds if p.get("measured", True) else "not measured"
            c = p.get("comparison")
            label = f"({p['key'].replace('_prime', '′')})"  # by key: claims are worded per version
            out[label] = holds + (f" {difference_cell(c)}" if c else "")
        return out

    left, right = verdicts(a), verdicts(b)
    return [(k, left.get(k, "–"), right.get(k, "–")) for k in dict.fromkeys([*left, *right])]


def _comparison_rows(a: dict[str, Any], b: dict[str, Any]) -> list[tuple[str, str, str]]:
    pairs = [
        (c["arm"], c["baseline"])
        for doc in (a, b)
        for c in doc.get("comparisons", [])
        if c["budget"] == ENDPOINT
    ]
    return [
        (
            f"{arm} − {baseline}",
            difference_cell(_endpoint(a, arm, baseline)),
            difference_cell(_endpoint(b, arm, baseline)),
        )
        for arm, baseline in dict.fromkeys(pairs)
    ]


def compare_studies(a: dict[str, Any], b: dict[str, Any]) -> dict[str, list[tuple[str, str, str]]]:
    """Sections of (row, study A, study B): design, preconditions, comparisons at the primary endpoint
    (points, paired difference [interval]); a row one study lacks shows `–` there."""
    return {
        "design": _design_rows(a, b),
        "preconditions": _precondition_rows(a, b),
        "comparisons at the primary endpoint (points)": _comparison_rows(a, b),
    }
