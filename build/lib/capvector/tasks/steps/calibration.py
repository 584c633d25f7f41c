"""Calibration before a study: the written rule that chooses its tasks, and the `calibration` artifact.

Pure parts (unit-tested on hand-made numbers): `apply_rule` judges each candidate task by pilot SFT's
success on validation goals, `split_tasks` deals the kept tasks into the downstream and extraction
sets by alternating down their ranking, `ladder` and `extraction_convergence` read the held-out
action loss of extraction runs of doubling length. The step `calibrate_task` registers all of it as
one `calibration` artifact whose parents are the validation evaluations, the extraction runs and
their held-out loss measurements; `calibration_markdown` renders it.

Input labels of the step: `eval/<seed>/<budget>` (validation evaluations of the pilot SFT runs),
`run/<steps>` (an extraction run θ_ft of that length) and `loss/<steps>/<half|end>` (its held-out
action loss at half and at the end of the run).
"""

from __future__ import annotations

import statistics
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, model_validator

from capvector.artifacts.scores import read_scores
from capvector.core.simulation.demos import VALIDATION_SEED_BASE
from capvector.tasks.runtime.step_kinds import StepCall, StepKind, step_task
from capvector.tasks.runtime.workspace import Workspace, provenance
from capvector.tasks.steps.held_out_loss import measured_loss

CALIBRATION_KIND = "calibration"
Curves = dict[str, dict[str, dict[str, float]]]
"""task -> seed -> budget (JSON keys: strings) -> success on validation goals, in points (0-100)."""


class TaskRule(BaseModel):
    """The written rule a task must pass to be studied: pilot SFT's success neither at floor nor at
    ceiling, and not decided by the seed."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    budgets: list[int] = Field(
        min_length=1,
        description="downstream steps at which each pilot SFT run is kept and tested on validation goals, "
        "ascending; the last is the run's length (downstream.steps). A task's score is its mean success "
        "over them (the area under its success-vs-steps curve, the study's primary endpoint)",
    )
    low: float = Field(
        15.0, ge=0, le=100, description="points; a task whose mean over seeds is below this is at floor"
    )
    high: float = Field(
        85.0, ge=0, le=100, description="points; a task whose mean over seeds is above this is at ceiling"
    )
    spread: float = Field(
        40.0,
        ge=0,
        description="points; a task with a pilot seed's score further than this from the mean over seeds "
        "is decided by the seed, not by the method, and is left out",
    )
    min_tasks_per_split: int = Field(
        6,
        ge=1,
        description="kept tasks needed in each of the extraction and downstream sets; with fewer the "
        "calibration says so and measures no extraction budget",
    )

    @model_validator(mode="after")
    def _ordered(self) -> TaskRule:
        if self.budgets != sorted(set(self.budgets)) or self.budgets[0] <= 0:
            raise ValueError(f"rule.budgets must be positive, distinct and ascending, got {self.budgets}")
        if self.low > self.high:
            raise ValueError(f"rule.low ({self.low:g}) is above rule.high ({self.high:g})")
        return self

    def text(self) -> str:
        """The rule in words, as the report states it."""
        return (
            f"SFT's mean success over budgets {self.budgets} (mean over pilot seeds) within "
            f"[{self.low:g}, {self.high:g}] % and no seed more than {self.spread:g} points from that mean; "
            "kept tasks ranked by that mean (ties: the candidates' order) and dealt alternately, 1st to "
            f"downstream, 2nd to extraction, ...; at least {self.min_tasks_per_split} tasks in each set"
        )


class Verdict(BaseModel):
    """One candidate task under the rule."""

    per_seed: dict[str, float]
    """Seed -> mean success over the budgets (points)."""
    mean: float
    farthest: float
    """The largest distance of a seed's score from `mean` (points)."""
    chosen: bool
    reason: str
    """Why it is left out (floor, ceiling, spread), or "kept"."""


class TaskSplit(BaseModel):
    ranking: list[str]
    """Kept tasks, best SFT mean first."""
    downstream: list[str]
    extraction: list[str]
    enough: bool
    shortfall: str | None = None
    """Why the sets are too small for a study, in words; None when they are not."""


def apply_rule(curves: Curves, seeds: list[int], rule: TaskRule) -> dict[str, Verdict]:
    """Each task's verdict; `curves` must hold every seed at every budget of the rule."""
    verdicts = {}
    for task, by_seed in curves.items():
        per_seed = {}
        for seed in map(str, seeds):
            points = by_seed.get(seed, {})
            missing = [b for b in rule.budgets if str(b) not in points]
            if missing:
                raise ValueError(f"calibration: {task} seed {seed} has no success at budgets {missing}")
            per_seed[seed] = statistics.fmean(points[str(b)] for b in rule.budgets)
        mean = statistics.fmean(per_seed.values())
        farthest = max(abs(v - mean) for v in per_seed.values())
        if mean < rule.low:
            reason = f"at floor ({mean:.1f} < {rule.low:g})"
        elif mean > rule.high:
            reason = f"at ceiling ({mean:.1f} > {rule.high:g})"
        elif farthest > rule.spread:
            reason = f"decided by the seed (a seed {farthest:.1f} points from the mean > {rule.spread:g})"
        else:
            reason = "kept"
        verdicts[task] = Verdict(
            per_seed=per_seed, mean=mean, farthest=farthest, chosen=reason == "kept", reason=reason
        )
    return verdicts


def split_tasks(verdicts: dict[str, Verdict], min_tasks: int) -> TaskSplit:
    """Kept tasks ranked by SFT mean (ties keep the verdicts' order), dealt alternately: 1st to
    downstream, 2nd to extraction, ... so both sets span the same difficulty."""
    kept = [t for t, v in verdicts.items() if v.chosen]
    # Means are averages of goal counts: rounded so that equal means in exact arithmetic tie here too.
    ranking = sorted(kept, key=lambda t: -round(verdicts[t].mean, 9))
    downstream, extraction = ranking[0::2], ranking[1::2]
    sizes = [f"{name} {len(s)}" for name, s in (("downstream", downstream), ("extraction", extraction))]
    enough = min(len(downstream), len(extraction)) >= min_tasks
    shortfall = None
    if not enough:
        shortfall = (
            f"{len(kept)} of {len(verdicts)} candidates pass the rule, too few for a study: "
            f"{', '.join(sizes)} tasks, at least {min_tasks} needed in each. Widen the candidates or "
            "the rule and calibrate again; no extraction budget was measured"
        )
    return TaskSplit(
        ranking=ranking, downstream=downstream, extraction=extraction, enough=enough, shortfall=shortfall
    )


def ladder(start: int, cap: int) -> list[int]:
    """Extraction budgets tried: `start`, doubling, the last one clipped to `cap`."""
    if not 0 < start <= cap:
        raise ValueError(f"extraction budgets: start ({start}) must be positive and at most the cap ({cap})")
    budgets = [start]
    while budgets[-1] < cap:
        budgets.append(min(2 * budgets[-1], cap))
    return budgets


def relative_drop(at_half: float, at_end: float) -> float:
    """How much the held-out loss fell over a run's second half, as a fraction of its value at half
    (negative: it rose). The study's precondition (a) reads the same fraction
    (capvector.tasks.steps.study_analysis)."""
    return (at_half - at_end) / at_half


class ExtractionRow(BaseModel):
    steps: int
    half: int
    loss_at_half: float
    loss_at_end: float
    relative_drop: float
    flat: bool


class ExtractionConvergence(BaseModel):
    tolerance: float
    budgets: list[int]
    """Every budget of the ladder (start, doubling, cap), tried or not."""
    rows: list[ExtractionRow]
    """The budgets run, in order, up to the first flat one."""
    steps: int | None
    """The first budget whose held-out loss moved less than `tolerance` over its second half; None:
    not converged by the cap."""
    verdict: str


def extraction_convergence(
    losses: dict[int, tuple[float, float]], budgets: list[int], tolerance: float
) -> ExtractionConvergence:
    """`losses`: steps -> (held-out loss at half, at the end) of the runs made, a prefix of `budgets`."""
    rows = []
    for steps in budgets:
        if steps not in losses:
            break
        half, end = losses[steps]
        drop = relative_drop(half, end)
        rows.append(
            ExtractionRow(
                steps=steps,
                half=steps // 2,
                loss_at_half=half,
                loss_at_end=end,
                relative_drop=drop,
                flat=abs(drop) < tolerance,
            )
        )
        if rows[-1].flat:
            break
    extra = sorted(set(losses) - {r.steps for r in rows})
    if extra:
        raise ValueError(f"extraction losses at {extra} steps: not a prefix of the ladder {budgets}")
    last = rows[-1] if rows else None
    moved = f"{100 * abs(last.relative_drop):.1f} % over the second half" if last else ""
    if last is None:
        steps, verdict = None, "not measured"
    elif last.flat:
        steps = last.steps
        verdict = f"converged at {steps} steps: held-out loss moved {moved} (< {100 * tolerance:g} %)"
    elif last.steps == budgets[-1]:
        steps = None
        verdict = (
            f"not converged by the cap ({last.steps} steps): held-out loss still moved {moved} "
            f"(tolerance {100 * tolerance:g} %)"
        )
    else:
        steps, verdict = None, f"not converged by {last.steps} steps (budgets above not run)"
    return ExtractionConvergence(
        tolerance=tolerance, budgets=budgets, rows=rows, steps=steps, verdict=verdict
    )


# ---------------------------------------------------------------------------- the step
class ExtractionLadder(BaseModel):
    model_config = ConfigDict(extra="forbid")
    budgets: list[int] = Field(min_length=1)
    tolerance: float = Field(gt=0, lt=1)


class CalibrationStepConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str
    candidates: list[str] = Field(min_length=1)
    seeds: list[int] = Field(min_length=1)
    rule: TaskRule
    extraction: ExtractionLadder
    config: dict[str, Any] = Field(default_factory=dict, description="the calibration's whole config")


def _parse(inputs: dict[str, str], kind: str) -> list[tuple[list[str], str]]:
    return [(k.split("/")[1:], v) for k, v in sorted(inputs.items()) if k.split("/")[0] == kind]


def validation_curves(workspace: Workspace, inputs: dict[str, str], candidates: list[str]) -> Curves:
    """Curves from the `eval/<seed>/<budget>` inputs: every one on validation goals, one protocol."""
    labelled = _parse(inputs, "eval")
    if not labelled:
        raise ValueError("calibration: no `eval/<seed>/<budget>` inputs")
    for _, e in labelled:
        seed_base = workspace.api.get(e).config["eval"]["seed_base"]
        if seed_base != VALIDATION_SEED_BASE:
            raise ValueError(
                f"calibration: evaluation {e[:12]} is not on validation goals (seeds {seed_base})"
            )
    scores = {s.evaluation_id: s for s in read_scores(workspace.api, evaluations=[e for _, e in labelled])}
    protocols = {scores[e].fingerprint for _, e in labelled}
    if len(protocols) != 1:
        raise ValueError(f"calibration: the evaluations are under {len(protocols)} protocols, not one")
    curves: Curves = {task: {} for task in candidates}
    for (seed, budget), e in labelled:
        rates = scores[e].success_rates
        missing = sorted(set(candidates) - set(rates))
        if missing:
            raise ValueError(f"calibration: evaluation {e[:12]} did not test {missing}")
        for task in candidates:
            curves[task].setdefault(seed, {})[budget] = 100 * rates[task]
    for task in curves:  # budgets ascending, as the rule lists them
        curves[task] = {
            s: dict(sorted(b.items(), key=lambda kv: int(kv[0]))) for s, b in curves[task].items()
        }
    return curves


def choose_tasks(
    workspace: Workspace, inputs: dict[str, str], cfg: CalibrationStepConfig
) -> tuple[Curves, dict[str, Verdict], TaskSplit]:
    """The curves of the validation evaluations among `inputs`, each task's verdict and the split. The
    flow calls it to know which extraction runs to make; the step, to record the same answer."""
    curves = validation_curves(workspace, inputs, cfg.candidates)
    verdicts = apply_rule(curves, cfg.seeds, cfg.rule)
    return curves, verdicts, split_tasks(verdicts, cfg.rule.min_tasks_per_split)


def extraction_losses(workspace: Workspace, inputs: dict[str, str]) -> dict[int, tuple[float, float]]:
    """steps -> (held-out loss at half, at the end) from the `loss/<steps>/<half|end>` inputs."""
    found: dict[int, dict[str, float]] = {}
    for (steps, where), m in _parse(inputs, "loss"):
        found.setdefault(int(steps), {})[where] = measured_loss(workspace, m)
    return {steps: (v["half"], v["end"]) for steps, v in sorted(found.items())}


def _calibrate(call: StepCall) -> str:
    workspace, inputs, cfg = call.workspace, call.inputs, call.config
    curves, verdicts, split = choose_tasks(workspace, inputs, cfg)
    convergence = extraction_convergence(
        extraction_losses(workspace, inputs), cfg.extraction.budgets, cfg.extraction.tolerance
    )
    doc = {
        "name": cfg.name,
        "config": cfg.config,
        "candidates": cfg.candidates,
        "seeds": cfg.seeds,
        "rule": {**cfg.rule.model_dump(mode="json"), "text": cfg.rule.text()},
        "curves": curves,
        "verdicts": {t: v.model_dump(mode="json") for t, v in verdicts.items()},
        "split": split.model_dump(mode="json"),
        "extraction": convergence.model_dump(mode="json"),
        "evaluations": {k: v for k, v in sorted(inputs.items()) if k.startswith("eval/")},
        "extraction_runs": {k: v for k, v in sorted(inputs.items()) if k.startswith("run/")},
        "selected_on": "validation goals (success) and held-out extraction demonstrations (loss)",
    }
    parents = [(v, _ROLES[k.split("/")[0]]) for k, v in sorted(inputs.items())]
    record = workspace.api.register_json(
        doc,
        kind=CALIBRATION_KIND,
        name=call.step,
        config={"cache_key": call.key},
        parents=list(dict.fromkeys(parents)),
        **provenance(),
    )
    return record.id


_ROLES = {"eval": "validation", "run": "extraction_run", "loss": "held_out_loss"}
CALIBRATE = StepKind("calibrate", CalibrationStepConfig, (), _calibrate)
calibrate_task = step_task(CALIBRATE)


# ---------------------------------------------------------------------------- the report
def preset_lines(doc: dict[str, Any]) -> list[str]:
    """What a study preset takes from the calibration (`--set` syntax; in a preset, the same keys)."""
    split = doc["split"]
    if not split["enough"]:
        return []
    lines = [
        f"splits.extraction=[{', '.join(split['extraction'])}]",
        f"splits.downstream=[{', '.join(split['downstream'])}]",
    ]
    steps = doc["extraction"]["steps"]
    if steps is not None:
        lines.append(f"extraction.steps={steps}")
    return lines


def calibration_markdown(doc: dict[str, Any]) -> str:
    """The calibration artifact in Markdown: the rule, the curves (task rows × budget columns, success
    averaged over seeds), each verdict, the sets, the extraction budget and its evidence."""
    rule, budgets, seeds = doc["rule"], doc["rule"]["budgets"], doc["seeds"]
    split, extraction = doc["split"], doc["extraction"]
    cfg = doc.get("config", {})
    sets = {t: "downstream" for t in split["downstream"]} | {t: "extraction" for t in split["extraction"]}
    lines = [
        f"# Calibration {doc['name']}: SFT learning curves per task (validation goals)",
        "",
        f"SFT from θ_pt on all {len(doc['candidates'])} candidates together, pilot seeds {seeds}"
        + _protocol(cfg)
        + ". Cells: success (%) averaged over seeds.",
        "",
        f"Rule: {rule['text']}.",
        "",
        "| task | " + " | ".join(f"SFT @ {b}" for b in budgets) + " | SFT mean | per seed | verdict | set |",
        "|---|" + "---|" * (len(budgets) + 4),
    ]
    for task, v in doc["verdicts"].items():
        cells = [
            f"{statistics.fmean(doc['curves'][task][str(s)][str(b)] for s in seeds):.0f}" for b in budgets
        ]
        per_seed = " / ".join(f"{x:.0f}" for x in v["per_seed"].values())
        lines.append(
            f"| {task} | " + " | ".join(cells) + f" | {v['mean']:.1f} | {per_seed} | "
            f"{'kept' if v['chosen'] else v['reason']} | {sets.get(task, '')} |"
        )
    lines += [
        "",
        f"Kept, ranked: {', '.join(split['ranking']) or 'none'}.",
        "",
        f"- D_down ({len(split['downstream'])}): {', '.join(split['downstream']) or 'none'}",
        f"- D_ext ({len(split['extraction'])}): {', '.join(split['extraction']) or 'none'}",
        "",
    ]
    if split["shortfall"]:
        lines += [f"**Not enough tasks for a study.** {split['shortfall']}.", ""]
    lines += _extraction_lines(extraction)
    pasted = preset_lines(doc)
    if pasted:
        lines += [
            "",
            "For the study preset (`--set` syntax; the same keys in YAML):",
            "",
            "```",
            *pasted,
            "```",
        ]
    return "\n".join(lines) + "\n"


def _protocol(cfg: dict[str, Any]) -> str:
    try:
        ev, data = cfg["evaluation"], cfg["data"]
        pretrain = cfg["pretrain"]["steps"]
        n_pt = len(cfg["splits"]["pretrain"])
    except (KeyError, TypeError):
        return ""
    transform = data.get("obs_transform", {}).get("kind", "identity")
    return (
        f"; θ_pt {pretrain} steps on {n_pt} tasks; {data['episodes_downstream']} demos per candidate; "
        f"{ev['validation_episodes_per_task']} validation goals per task, horizon {ev['horizon']}; "
        f"observation transform `{transform}`"
    )


def _extraction_lines(extraction: dict[str, Any]) -> list[str]:
    lines = [
        "## Extraction budget",
        "",
        f"θ_ft on D_ext at budgets {extraction['budgets']} (each its own run from θ_pt, stopping at the "
        f"first whose held-out action loss moved less than {100 * extraction['tolerance']:g} % over its "
        f"second half): **{extraction['verdict']}**.",
    ]
    if extraction["rows"]:
        lines += [
            "",
            "| steps | loss @ half | loss @ end | moved over the second half | flat |",
            "|---|---|---|---|---|",
        ]
        for r in extraction["rows"]:
            lines.append(
                f"| {r['steps']} | {r['loss_at_half']:.4f} | {r['loss_at_end']:.4f} | "
                f"{-100 * r['relative_drop']:+.1f} % | {'yes' if r['flat'] else ''} |"
            )
    return lines


def load_calibration_doc(workspace: Workspace, calibration_id: str) -> dict[str, Any]:
    record = workspace.api.get(calibration_id)
    if record.kind != CALIBRATION_KIND:
        raise ValueError(f"{calibration_id[:12]} is a {record.kind}, not a calibration")
    return workspace.api.store.open_json(record.id)
