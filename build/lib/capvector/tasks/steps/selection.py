"""Step: choose values (an lr, α, λ) on validation goals, recorded as a `selection` artifact.

The selection's parents are the validation evaluations it was chosen from, and a step trained or
merged with a chosen value takes the selection as an input (role `selected_by`), so
`capvector lineage` of any checkpoint shows why each value was used. Test goals never enter: the
candidates' evaluations must be under one protocol, and the flow passes validation protocols only.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, Field, model_validator

from capvector.artifacts.scores import read_scores
from capvector.tasks.runtime.step_kinds import StepCall, StepKind, step_task
from capvector.tasks.runtime.workspace import Workspace, provenance
from capvector.tasks.steps.held_out_loss import measured_loss

SELECTION_KIND = "selection"
RULE = (
    "highest mean validation success over tasks (and over the candidate's budgets when it has several: "
    "the study's endpoint is the mean over its declared budgets); a tie goes to the lower held-out loss "
    "where measured (a saturated validation set cannot tell candidates apart), then to the earlier candidate"
)


class Candidate(BaseModel):
    """One point of the grid: its values, the input labels of its validation evaluations (one per budget
    its endpoint averages) and, optionally, of a held-out loss measurement
    (capvector.tasks.steps.held_out_loss) that
    breaks ties."""

    values: dict[str, Any]
    evaluations: list[str] = Field(min_length=1)
    tiebreak: str | None = None


class SelectionConfig(BaseModel):
    name: str = Field(min_length=1, description="what is chosen, e.g. 'extraction lr'")
    candidates: list[Candidate] = Field(min_length=1)
    context: dict[str, Any] = Field(default_factory=dict, description="e.g. the arm and seed")

    @model_validator(mode="after")
    def _distinct(self) -> SelectionConfig:
        labels = [e for c in self.candidates for e in c.evaluations]
        if len(set(labels)) != len(labels):
            raise ValueError(f"selection {self.name!r}: candidates share an evaluation label: {labels}")
        if len({c.tiebreak is None for c in self.candidates}) > 1:
            raise ValueError(
                f"selection {self.name!r}: some candidates have a tiebreak measurement, others not"
            )
        return self


def _candidates_given(step: str, inputs: dict[str, str], cfg: SelectionConfig) -> None:
    missing = [x for c in cfg.candidates for x in (*c.evaluations, c.tiebreak) if x and x not in inputs]
    if missing:
        raise ValueError(f"step {step!r}: no input for candidate evaluation(s) {missing}")


def _select(call: StepCall) -> str:
    workspace, step, inputs, cfg = call.workspace, call.step, call.inputs, call.config
    per_candidate = [[inputs[e] for e in c.evaluations] for c in cfg.candidates]
    eval_ids = [e for ids in per_candidate for e in ids]
    scores = {s.evaluation_id: s for s in read_scores(workspace.api, evaluations=eval_ids)}
    protocols = {scores[e].fingerprint for e in eval_ids}
    if len(protocols) != 1:
        raise ValueError(f"step {step!r}: candidates were evaluated under {len(protocols)} protocols")
    rows = [
        {
            **c.values,
            "evaluation_ids": ids,
            "checkpoint_ids": [scores[e].checkpoint_id for e in ids],
            "validation_success": sum(scores[e].mean_success for e in ids) / len(ids),
            **({"held_out_loss": measured_loss(workspace, inputs[c.tiebreak])} if c.tiebreak else {}),
        }
        for c, ids in zip(cfg.candidates, per_candidate, strict=True)
    ]
    # max keeps the first of equals
    best = max(rows, key=lambda r: (r["validation_success"], -r.get("held_out_loss", 0.0)))
    doc = {
        "name": cfg.name,
        **cfg.context,
        "parameters": sorted({k for c in cfg.candidates for k in c.values}),
        "grid": rows,
        "best": best,
        "rule": RULE,
        "selected_on": "validation goals",
        "protocol": protocols.pop(),
    }
    record = workspace.api.register_json(
        doc,
        kind=SELECTION_KIND,
        name=step,
        config={"cache_key": call.key},
        parents=[(e, "validation") for e in dict.fromkeys(eval_ids)]
        + [(inputs[c.tiebreak], "tiebreak") for c in cfg.candidates if c.tiebreak],
        **provenance(),
    )
    return record.id


def chosen(workspace: Workspace, selection_id: str) -> dict[str, Any]:
    """The chosen candidate's values (as given in the config), e.g. {"alpha": 1.1, "lambda": 0.01}; a
    grid whose cells name different parameters (λ relative or absolute) gives the chosen cell's."""
    doc = workspace.api.store.open_json(selection_id)
    return {k: doc["best"][k] for k in doc["parameters"] if k in doc["best"]}


SELECT = StepKind("select", SelectionConfig, (), _select, check=_candidates_given)
run_select = SELECT.run
select_task = step_task(SELECT)
