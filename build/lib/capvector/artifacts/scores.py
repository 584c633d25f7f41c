"""The one way to read a score: from the catalogue, where it is derived from the evaluation's document.

An evaluation artifact's document (its per-episode records) is the source of truth; the catalogue's
`eval_tasks` rows are derived from it whenever it is indexed (registration, sync, rebuild). Sidecars
of evaluations recorded before this module carry their own `mean_success`/`success_rates`: nothing
reads them, so an edited or stale copy there cannot disagree with what a report, sweep or CLI shows.
"""

from __future__ import annotations

import statistics
from collections.abc import Iterable
from datetime import datetime
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel, ConfigDict, computed_field

from capvector.artifacts.api import ArtifactsAPI
from capvector.artifacts.catalogue import EVALUATION_KIND, load_doc, rows_for

if TYPE_CHECKING:
    import pandas as pd

SCORES_SELECT = """
SELECT evaluation_id, checkpoint_id, fingerprint, evaluated_at, task, success_rate, n_episodes
FROM eval_tasks
WHERE list_contains($evaluations::VARCHAR[], evaluation_id)
   OR list_contains($checkpoints::VARCHAR[], checkpoint_id)
"""


class EvaluationScores(BaseModel):
    """One evaluation's scores under its protocol: success rate and episode count per task."""

    model_config = ConfigDict(frozen=True)
    evaluation_id: str
    checkpoint_id: str
    fingerprint: str
    evaluated_at: datetime
    success_rates: dict[str, float]
    episodes: dict[str, int]

    @computed_field  # type: ignore[prop-decorator]
    @property
    def mean_success(self) -> float:
        """Unweighted over tasks, as the evaluation itself reports it."""
        return statistics.fmean(self.success_rates.values())


def read_scores(
    api: ArtifactsAPI, *, evaluations: Iterable[str] = (), checkpoints: Iterable[str] = ()
) -> list[EvaluationScores]:
    """Scores of the `evaluations` and of every evaluation of the `checkpoints` (full ids), oldest first.

    A named evaluation without rows yet (registered by another process while the catalogue was locked:
    its row waits for that process or the next catch-up) is derived from its document here, by the
    same `rows_for` the catalogue uses; an id that is no evaluation is an error."""
    evaluations, checkpoints = list(dict.fromkeys(evaluations)), list(dict.fromkeys(checkpoints))
    rows: list[dict[str, Any]] = api.query(
        SCORES_SELECT, {"evaluations": evaluations, "checkpoints": checkpoints}
    ).to_dict("records")
    for eval_id in set(evaluations) - {r["evaluation_id"] for r in rows}:
        record = api.get(eval_id)
        if record.kind != EVALUATION_KIND:
            raise ValueError(f"{eval_id[:12]} is a {record.kind}, not an evaluation: it has no scores")
        derived = rows_for(record, load_doc(api.store, record))["eval_tasks"]
        if not derived:
            raise ValueError(f"evaluation {eval_id[:12]} has no episodes: it has no scores")
        rows.extend(derived)
    by_evaluation: dict[str, dict[str, Any]] = {}
    for r in sorted(rows, key=lambda r: (r["evaluated_at"], r["evaluation_id"], r["task"])):
        scores = by_evaluation.setdefault(
            r["evaluation_id"],
            {
                "evaluation_id": r["evaluation_id"],
                "checkpoint_id": r["checkpoint_id"],
                "fingerprint": r["fingerprint"],
                "evaluated_at": r["evaluated_at"],
                "success_rates": {},
                "episodes": {},
            },
        )
        scores["success_rates"][r["task"]] = float(r["success_rate"])
        scores["episodes"][r["task"]] = int(r["n_episodes"])
    return [EvaluationScores.model_validate(s) for s in by_evaluation.values()]


EPISODES_SELECT = """
SELECT evaluation_id, task, seed, success FROM eval_episodes
WHERE list_contains($evaluations::VARCHAR[], evaluation_id)
"""


def read_episodes(api: ArtifactsAPI, evaluations: Iterable[str]) -> pd.DataFrame:
    """Every episode of the `evaluations` (full ids): evaluation_id, task, seed (the goal), success.

    From the catalogue, like `read_scores`; an evaluation whose rows are not indexed yet is derived from
    its document by the same `rows_for`."""
    import pandas as pd  # a step that reads episodes needs it; a warm run's imports do not

    evaluations = list(dict.fromkeys(evaluations))
    frame = api.query(EPISODES_SELECT, {"evaluations": evaluations})
    missing = set(evaluations) - set(frame["evaluation_id"])
    extra = []
    for eval_id in sorted(missing):
        record = api.get(eval_id)
        if record.kind != EVALUATION_KIND:
            raise ValueError(f"{eval_id[:12]} is a {record.kind}, not an evaluation: it has no episodes")
        extra += rows_for(record, load_doc(api.store, record))["eval_episodes"]
    if extra:
        frame = pd.concat([frame, pd.DataFrame(extra)[list(frame.columns)]], ignore_index=True)
    return frame.astype({"seed": "int64", "success": "bool"})
