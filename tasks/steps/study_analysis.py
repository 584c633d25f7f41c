"""Step: analyse a study — preconditions, paired comparisons, curves, design MDD — into a `study` artifact.

Inputs are keyed by the typed keys of capvector.tasks.study_inputs (the compared runs' test evaluations at
every budget, D_ext validations, held-out losses, γ^d and θ_ft^d, selections), each read back as its
model. The primary endpoint is each goal's
success averaged over the declared budgets (`capvector.stats.paired_differences.ENDPOINT`). A `gate`
stage analyses the arms that test preconditions (c) and (c′) before CapVector's arms run
(`gate_passed`). Scores come from the evaluations' episodes (capvector.artifacts.scores.read_episodes); the
statistics are capvector.stats.paired_differences'. The document holds no timings (its id depends on
results only); the rendered report reads speeds from the checkpoints' records.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
from pydantic import BaseModel, ConfigDict, model_serializer

from capvector.artifacts.scores import read_episodes, read_scores
from capvector.core.vectors.safetensors_io import Checkpoint
from capvector.core.vectors.vector_ops import stable_dot
from capvector.stats.paired_differences import (
    ENDPOINT,
    SHARED_DRAW,
    Comparison,
    CurvePoint,
    Design,
    VarianceComponents,
    endpoint_rows,
    paired_difference,
    smallest_design,
    success_curve,
    t_quantile,
)
from capvector.tasks.runtime.step_kinds import StepCall, StepKind, step_task
from capvector.tasks.runtime.workspace import Workspace, provenance
from capvector.tasks.steps.held_out_loss import measured_loss, merge_error
from capvector.tasks.steps.study_forms import RankSpread, endpoints, rank_spreads
from capvector.tasks.study_inputs import (
    CapabilityVector,
    DownstreamLoss,
    ExtractionValidation,
    HeldOutLoss,
    Pretrained,
    ReplicateVector,
    Selection,
    StandardRun,
    TestEvaluation,
    inputs_of,
)

STUDY_KIND = "study"
COMPARED = (  # (arm, baseline): the report's headline, then the controls
    ("capvector", "sft"),
    ("capvector", "aux"),
    ("capvector", "meta_sft"),
    ("capvector", "null_capvector"),
    ("aux", "sft"),
    ("sft_from_ao", "sft_from_ft"),
    ("sft_from_ao", "sft"),
    ("meta_sft", "sft"),
    ("meta_sft_dose", "sft"),
    ("meta_sft_dose", "meta_sft"),
    ("capvector_lora", "sft_lora"),  # the adapter forms, each against its SFT form (a study variant)
    ("capvector_lora_sp", "sft_lora_sp"),
    ("capvector_adalora", "sft_adalora"),
)


def compared_pairs(design: StudyDesign) -> tuple[tuple[str, str], ...]:
    """Every (arm, baseline) the study compares: the fixed ones, each variant against full fine-tuning
    (`sft`), then the pairs the study declares (`study.compare`)."""
    return COMPARED + tuple((name, "sft") for name in design.variants) + tuple(map(tuple, design.compare))


GATING = ("c", "c_prime")
"""The preconditions CapVector's arms wait for. (b) is reported, not gating: on the calibrated testbeds
θ_ft sits at the D_ext ceiling (88–98 %), where (b) cannot show a difference that (c′) downstream can."""


class StudyDesign(BaseModel):
    """What the analysis needs besides the evaluations: the declared endpoints and the choices made."""

    model_config = ConfigDict(extra="forbid")
    name: str
    arms: list[str]
    variants: dict[str, dict[str, Any]] = {}
    """Variant name -> its declaration (`arm`, `set`, `lrs`): arms from θ_pt compared against `sft`."""
    compare: list[tuple[str, str]] = []
    """Declared (arm, baseline) pairs among the variants, compared besides each variant against `sft`."""
    draws: list[int]
    """The γ draws; empty for a study whose arms need no γ."""
    seeds: list[int]
    endpoint_budgets: list[int]
    """The primary endpoint: mean success over these budgets (the final one included)."""
    final_budget: int
    extraction_steps: int
    flat_tolerance: float
    non_inferiority_margin: float
    n_boot: int
    gate: bool = True
    draws_per_replicate: int = 1
    """K > 1: CapVector's arms ran per replicate (the mean of K draws); their `draw` is the replicate."""
    stage: Literal["gate", "final"] = "final"
    chosen: dict[str, float]
    grids: dict[str, list[float]]
    given: bool = False
    """True: nothing was chosen (no tuning seeds); `chosen` holds the values the preset gave."""

    @model_serializer(mode="wrap")
    def _given_only_when_true(self, handler: Any) -> dict[str, Any]:
        """`given` is written only when true: a study that chose its values is stored as before."""
        data = handler(self)
        if not data.get("given"):
            data.pop("given", None)
        return data

    def at_edge(self) -> list[str]:
        """Choices at an end of a grid of 3 or more values (a wider grid might have chosen beyond)."""
        return [
            k
            for k, v in self.chosen.items()
            if len(self.grids.get(k, [])) >= 3 and v in (min(self.grids[k]), max(self.grids[k]))
        ]


class Precondition(BaseModel):
    key: str
    claim: str
    holds: bool | None
    """True: shown; False: contradicted; None: not shown either way (the CI includes zero)."""
    measured: bool = True
    """False: the study did not measure it (an arm not run, a gate that stopped before it, one draw)."""
    detail_values: dict[str, float] = {}
    detail: str
    comparison: Comparison | None = None


class LossComparison(BaseModel):
    """`arm` − `baseline` in held-out action loss on D_down (lower is better), paired by draw and seed
    (a shared baseline's run s pairs with every draw's run s); a t interval over the pairs, which
    treats them as independent (approximate when a shared baseline's run serves several draws)."""

    arm: str
    baseline: str
    difference: float
    ci_low: float
    ci_high: float
    n_pairs: int
    arm_mean: float
    baseline_mean: float


class MergeError(BaseModel):
    """An arm's dense-merge error: merged − as-trained held-out action loss of its compared runs (LoRA-SP
    checkpoints are evaluated with their adapter; a merged checkpoint is an approximation of it), the mean
    over runs with a 95 % t interval over runs."""

    mean: float
    ci_low: float
    ci_high: float
    n_runs: int


class RunPoint(BaseModel):
    """One compared run's mean success (points) over its test goals at one budget (budget 0: the
    checkpoint it started from)."""

    draw: int
    seed: int
    budget: int
    success: float


class TaskEndpoint(BaseModel):
    """An arm's primary endpoint on one task: the mean over its runs of each run's mean over the task's
    goals, a 95 % t interval over runs (clipped to 0-100; NaN from one run), and the n behind it. Runs,
    not goals, are the unit: one run's goals are not independent draws of the arm's effect."""

    mean: float
    ci_low: float
    ci_high: float
    n_runs: int
    n_goals: int


class StudyReport(BaseModel):
    design: StudyDesign
    gate: str | None = None
    """Why CapVector's arms did not run (the gate failed), or None (they ran, or no gate)."""
    goals_per_task: int
    tasks: list[str]
    preconditions: list[Precondition]
    comparisons: list[Comparison]
    curves: dict[str, list[CurvePoint]]
    selections: dict[str, str]
    convergence: list[dict[str, Any]]
    heldout_loss: list[LossComparison] = []
    """The continuous secondary endpoint: held-out action loss of the compared runs' final checkpoints."""
    merge_errors: dict[str, MergeError] = {}
    """Arm -> its dense merge's error, for arms whose checkpoints are evaluated as adapters (LoRA-SP)."""
    per_task: dict[str, dict[str, float]] = {}
    """Arm -> task -> mean success (points) at the primary endpoint, over draws, seeds and goals."""
    per_task_intervals: dict[str, dict[str, TaskEndpoint]] = {}
    """Arm -> task -> its endpoint with an interval over runs and n (the per-task figure's bars)."""
    run_curves: dict[str, list[RunPoint]] = {}
    """Arm -> each run's success at each budget (the points beside the curves' means)."""
    final_checkpoints: dict[str, list[str]]
    """Arm -> its runs' final checkpoints (where the rendered report reads time per step)."""
    endpoints: dict[str, CurvePoint] = {}
    """Arm -> its mean success at the primary endpoint with a 95 % interval."""
    rank_spread: list[RankSpread] = []
    """With variants: each form's best − worst variant at the endpoint (capvector.tasks.steps.study_forms)."""
    designs_for_5_points: dict[str, Design | None]
    """`arm-baseline` -> the cheapest design, at least as large as this one and never under 2 draws × 2
    seeds, whose MDD at the primary endpoint would be ≤ 5 points, sized from this study's variance
    components (None: none in the searched grid; components this study could not separate count as 0,
    so it is a lower bound then)."""

    def comparison(self, arm: str, baseline: str, budget: int = ENDPOINT) -> Comparison | None:
        """`arm` − `baseline` at `budget` (the primary endpoint by default), or None where not compared."""
        wanted = (arm, baseline, budget)
        return next((c for c in self.comparisons if (c.arm, c.baseline, c.budget) == wanted), None)


def _episodes(workspace: Workspace, labelled: list[tuple[dict[str, Any], str]]) -> pd.DataFrame:
    """One row per episode with the paired_differences columns; `goal` is the episode's env seed."""
    frame = read_episodes(workspace.api, [e for _, e in labelled]).rename(columns={"seed": "goal"})
    keys = pd.DataFrame([{**k, "evaluation_id": e} for k, e in labelled])
    # many to many: a run's start (budget 0) is one evaluation counted for every seed
    rows = frame.merge(keys, on="evaluation_id", validate="many_to_many")
    return rows[["arm", "draw", "seed", "task", "goal", "budget", "success"]]


def _verdict(c: Comparison, sign: int = 1) -> bool | None:
    """Shown (CI on the claimed side of 0), contradicted (CI on the other side) or neither."""
    low, high = sign * c.ci_low, sign * c.ci_high
    low, high = min(low, high), max(low, high)
    return True if low > 0 else False if high < 0 else None


def _compare(episodes: pd.DataFrame, arm: str, baseline: str, budget: int, n_boot: int) -> Comparison | None:
    arms = set(episodes["arm"])
    if arm not in arms or baseline not in arms:
        return None
    return paired_difference(episodes, arm, baseline, budget, n_boot=n_boot)


def _convergence(workspace: Workspace, inputs: dict[str, str], design: StudyDesign) -> list[dict[str, Any]]:
    losses: dict[tuple[str, int], dict[int, float]] = {}
    for k, m in inputs_of(inputs, HeldOutLoss):
        losses.setdefault((k.which, k.draw), {})[k.budget] = measured_loss(workspace, m)
    rows = []
    for (which, draw), by_budget in sorted(losses.items()):
        half, final = min(by_budget), max(by_budget)
        drop = (by_budget[half] - by_budget[final]) / by_budget[half]
        rows.append(
            {
                "run": which,
                "draw": draw,
                "loss_at": {str(b): v for b, v in sorted(by_budget.items())},
                "relative_drop": drop,  # over the second half; negative: the loss rose (overfitting)
                "flat": abs(drop) < design.flat_tolerance,
                "final_step": final,
            }
        )
    return rows


def _preconditions(
    workspace: Workspace,
    inputs: dict[str, str],
    design: StudyDesign,
    episodes_ext: pd.DataFrame,
    comparisons: list[Comparison],
    convergence: list[dict[str, Any]],
) -> list[Precondition]:
    flat = [r for r in convergence if r["flat"]]
    drops = ", ".join(
        f"θ_{'ft' if r['run'] == 'standard' else 'ao'}^{r['draw']} {-100 * r['relative_drop']:+.1f} %"
        for r in convergence
    )
    how = "given by the preset" if design.given else "chosen on validation"
    result = [
        Precondition(
            key="a",
            claim=f"the extraction runs converge (lr {how.replace('validation', 'D_ext validation')}; "
            "held-out action loss flat "
            f"over the second half: moved < {100 * design.flat_tolerance:.0f} %); reported, not required: "
            "longer extraction made γ noisier, (e) measures what CapVector needs",
            holds=len(flat) == len(convergence) if convergence else None,
            detail=f"lr {design.chosen['extraction_lr']:g} {how}; held-out loss change over "
            f"the second half: {drops}",
        )
    ]
    n_boot = design.n_boot
    ext = _compare(episodes_ext, "ao", "ft", 0, n_boot)
    result.append(
        Precondition(
            key="b",
            claim="auxiliary SFT beats SFT on D_ext validation goals (θ_ao vs θ_ft; reported, not gating: "
            "on the calibrated testbeds θ_ft sits near D_ext's ceiling, where (b) cannot show a difference)",
            holds=_verdict(ext) if ext else None,
            detail=ext.summary() if ext else "not measured",
            comparison=ext,
            measured=ext is not None,
        )
    )
    result.append(
        _from_comparison(
            comparisons,
            "c",
            "downstream SFT from θ_ao beats SFT from θ_ft on D_down (something to transfer)",
            ("sft_from_ao", "sft_from_ft"),
        )
    )
    result.append(
        _from_comparison(
            comparisons,
            "c_prime",
            "downstream SFT from θ_ao beats SFT from θ_pt on D_down (θ_ao's weights hold something "
            "beyond θ_pt: what a method that only changes the starting weights can carry)",
            ("sft_from_ao", "sft"),
        )
    )
    merged = _compare(episodes_ext, "meta", "pt", 0, n_boot)
    margin = design.non_inferiority_margin
    not_worse = None
    if merged is not None:  # non-inferiority: shown when the CI excludes a loss of `margin` points
        not_worse = True if merged.ci_low > -margin else False if merged.ci_high < 0 else None
    result.append(
        Precondition(
            key="d",
            claim=f"θ_meta is not worse than θ_pt before downstream training (D_ext validation goals; "
            f"CI above −{margin:g} points)",
            holds=not_worse,
            detail=merged.summary() if merged else "not measured (θ_meta is merged after the gate)",
            comparison=merged,
            measured=merged is not None,
        )
    )
    result.append(_reproducibility(workspace, inputs))
    return result


def _from_comparison(
    comparisons: list[Comparison], key: str, claim: str, arms: tuple[str, str]
) -> Precondition:
    """A precondition that is an endpoint comparison of two downstream arms: shown when its interval
    lies above 0."""
    found = next((c for c in comparisons if (c.arm, c.baseline) == arms and c.budget == ENDPOINT), None)
    return Precondition(
        key=key,
        claim=claim,
        holds=_verdict(found) if found else None,
        detail=found.summary() if found else f"not run (arms {arms[0]}, {arms[1]})",
        comparison=found,
        measured=found is not None,
    )


def _reproducibility(workspace: Workspace, inputs: dict[str, str]) -> Precondition:
    """(e): how much of γ is signal. With γ^d = s + noise^d (noise independent between draws),
    ⟨γ^d, γ^d′⟩ estimates ‖s‖² and cos(γ^d, γ^d′) the signal fraction ρ; jackknife intervals over draws
    (3 draws or more). The mean of K draws then points at s with cos √(Kρ / (Kρ + 1 − ρ))."""
    vectors = {k.draw: workspace.path(v) for k, v in inputs_of(inputs, CapabilityVector)}
    standard = {k.draw: workspace.path(v) for k, v in inputs_of(inputs, StandardRun)}
    pretrained = [workspace.path(v) for _, v in inputs_of(inputs, Pretrained)]
    claim = (
        "γ carries a reproducible direction: the signal fraction ρ̂ (mean pairwise cos(γ^d, γ^d′)) has its "
        "interval above 0"
    )
    if len(vectors) < 2:
        detail = "needs at least 2 γ draws"
        return Precondition(key="e", claim=claim, holds=None, detail=detail, measured=False)
    gammas = {d: _flat(Checkpoint(p)) for d, p in sorted(vectors.items())}
    names = sorted(next(iter(gammas.values())))
    flat = {d: np.concatenate([g[n] for n in names]) for d, g in gammas.items()}
    fts = {d: np.concatenate(list(_flat(Checkpoint(p), names).values())) for d, p in sorted(standard.items())}
    draws = sorted(flat)
    with_self = itertools.combinations_with_replacement(draws, 2)
    dots = {(a, b): stable_dot(flat[a], flat[b]) for a, b in with_self}
    norms = {d: math.sqrt(dots[d, d]) for d in draws}

    values, intervals = _signal_fraction(draws, dots, norms)
    noise = [
        math.sqrt(stable_dot(fts[a] - fts[b], fts[a] - fts[b]))
        for a, b in itertools.combinations(draws, 2)
        if a in fts and b in fts
    ]
    values["seed_noise_norm"] = float(np.mean(noise)) if noise else math.nan
    reference = ""
    if pretrained:
        cosines = _ft_reference_cosines(pretrained[0], names, draws, flat, fts, norms)
        values["cos_ft_reference"] = float(np.mean(cosines))
        reference = f"; cos(γ^d, θ_ft^d − θ_pt) {', '.join(f'{c:+.2f}' for c in cosines)}"
    replicates = _replicate_agreement(workspace, inputs, names, len(draws), values)
    holds = None if "rho_low" not in values else True if values["rho_low"] > 0 else None
    detail = (
        f"ρ̂ {values['rho']:.2f}{intervals or ' (an interval needs 3 draws)'}; so the mean of these "
        f"{len(draws)} draws has cos {values['mean_vector_cos']:.2f} with the signal; ‖γ‖ "
        f"{', '.join(f'{n:.2f}' for n in norms.values())} against ‖θ_ft^d − θ_ft^d′‖ "
        f"{', '.join(f'{n:.2f}' for n in noise) or 'not measured'}{reference}{replicates}"
    )
    return Precondition(
        key="e", claim=claim, holds=holds, detail=detail, detail_values=values, measured=len(draws) >= 3
    )


def _signal_fraction(
    draws: list[int], dots: dict[tuple[int, int], float], norms: dict[int, float]
) -> tuple[dict[str, float], str]:
    """ρ̂, ‖ŝ‖, the draws' norms and pairwise cosines, with jackknife intervals from 3 draws on; the
    detail's text for the intervals ("" without them)."""

    def signal(kept: list[int]) -> tuple[float, float]:
        """(ρ̂, ‖ŝ‖²) over the pairs of `kept` draws."""
        pairs = list(itertools.combinations(kept, 2))
        scale = [norms[a] * norms[b] for a, b in pairs]
        cos = [dots[p] / n if n else math.nan for p, n in zip(pairs, scale, strict=True)]
        return float(np.mean(cos)), float(np.mean([dots[p] for p in pairs]))

    rho, square = signal(draws)
    values = {
        "rho": rho,
        "signal_norm": math.sqrt(max(square, 0.0)),
        "gamma_norm": float(np.mean(list(norms.values()))),
    }
    values["mean_vector_cos"] = _mean_vector_cos(len(draws), rho)
    values |= {f"gamma_norm_draw_{d}": n for d, n in norms.items()}  # per draw, for the γ figure
    values |= {
        f"cos_draws_{a}_{b}": dots[a, b] / (norms[a] * norms[b]) if norms[a] * norms[b] else math.nan
        for a, b in itertools.combinations(draws, 2)
    }
    if len(draws) < 3:
        return values, ""
    jack = np.array([signal([d for d in draws if d != left]) for left in draws])
    half = t_quantile(0.975, len(draws) - 1) * np.sqrt((len(draws) - 1) * jack.var(axis=0))
    values |= {"rho_low": rho - half[0], "rho_high": rho + half[0]}
    low, high = square - half[1], square + half[1]
    values |= {"signal_norm_low": math.sqrt(max(low, 0.0)), "signal_norm_high": math.sqrt(max(high, 0.0))}
    intervals = (
        f" [{values['rho_low']:+.2f}, {values['rho_high']:+.2f}]; ‖ŝ‖ {values['signal_norm']:.2f} "
        f"[{values['signal_norm_low']:.2f}, {values['signal_norm_high']:.2f}] (95 % jackknife over draws)"
    )
    return values, intervals


def _ft_reference_cosines(
    pretrained: Path,
    names: list[str],
    draws: list[int],
    flat: dict[int, np.ndarray],
    fts: dict[int, np.ndarray],
    norms: dict[int, float],
) -> list[float]:
    """cos(γ^d, θ_ft^d − θ_pt) for each draw with a standard run: how far γ points along plain
    fine-tuning's own update."""
    base = np.concatenate(list(_flat(Checkpoint(pretrained), names).values()))
    cosines = []
    for d in draws:
        if d in fts:
            delta = fts[d] - base
            scale = math.sqrt(stable_dot(delta, delta)) * norms[d]
            cosines.append(stable_dot(flat[d], delta) / scale if scale else math.nan)
    return cosines


def _replicate_agreement(
    workspace: Workspace, inputs: dict[str, str], names: list[str], n_draws: int, values: dict[str, float]
) -> str:
    """With replicate vectors γ̄^r: their mean pairwise cosine against what ρ̂ predicts for means of
    K draws (K ρ / (K ρ + 1 − ρ)), added to `values`; the detail's sentence ("" without replicates)."""
    means = {k.replicate: workspace.path(v) for k, v in inputs_of(inputs, ReplicateVector)}
    if len(means) < 2:
        return ""
    flat = {r: np.concatenate(list(_flat(Checkpoint(p), names).values())) for r, p in means.items()}
    cos = [
        stable_dot(flat[a], flat[b]) / math.sqrt(stable_dot(flat[a], flat[a]) * stable_dot(flat[b], flat[b]))
        for a, b in itertools.combinations(sorted(flat), 2)
    ]
    k = n_draws // len(means)
    values["replicate_cos"] = float(np.mean(cos))
    values["replicate_cos_predicted"] = _mean_vector_cos(k, values["rho"]) ** 2
    return (
        f"; {len(means)} replicates of {k} draws: mean cos(γ̄^r, γ̄^r′) {values['replicate_cos']:.2f} "
        f"(ρ̂ predicts {values['replicate_cos_predicted']:.2f})"
    )


def _mean_vector_cos(k: int, rho: float) -> float:
    """cos(γ̄_K, s) of the mean of K draws whose signal fraction is ρ (clipped to [0, 1])."""
    rho = min(max(rho, 0.0), 1.0)
    return math.sqrt(k * rho / (k * rho + 1 - rho)) if rho > 0 else 0.0


def _flat(checkpoint: Checkpoint, names: list[str] | None = None) -> dict[str, np.ndarray]:
    """Float tensors of a (small) checkpoint as flat float64 arrays, by name."""
    tensors = {n: checkpoint.get(n) for n in (names if names is not None else checkpoint.keys())}
    return {n: t.double().ravel().numpy() for n, t in tensors.items() if t.is_floating_point()}


def _per_task_intervals(episodes: pd.DataFrame) -> dict[str, dict[str, TaskEndpoint]]:
    """`TaskEndpoint`s of every arm and task at the primary endpoint."""
    endpoint = episodes[episodes["budget"] == ENDPOINT]
    out: dict[str, dict[str, TaskEndpoint]] = {}
    for (arm, task), rows in endpoint.groupby(["arm", "task"]):
        runs = 100 * rows.groupby(["draw", "seed"])["success"].mean().to_numpy()
        n, mean = len(runs), float(runs.mean())
        half = t_quantile(0.975, n - 1) * float(runs.std(ddof=1)) / math.sqrt(n) if n > 1 else math.nan
        low, high = (math.nan, math.nan) if n < 2 else (max(0.0, mean - half), min(100.0, mean + half))
        out.setdefault(str(arm), {})[str(task)] = TaskEndpoint(
            mean=mean, ci_low=low, ci_high=high, n_runs=n, n_goals=int(rows["goal"].nunique())
        )
    return out


def gate_passed(workspace: Workspace, report_id: str) -> bool:
    """Whether a gate-stage analysis found preconditions (c) and (c′) shown (intervals above 0)."""
    report = StudyReport.model_validate(workspace.api.store.open_json(report_id))
    return report.gate is None


def analyse(workspace: Workspace, inputs: dict[str, str], design: StudyDesign) -> StudyReport:
    tests = [(k.model_dump(), e) for k, e in inputs_of(inputs, TestEvaluation)]
    if not tests:
        raise ValueError("a study analysis needs test evaluations (inputs test/<arm>/<draw>/<seed>/<budget>)")
    episodes = _episodes(workspace, tests)
    episodes = pd.concat([episodes, endpoint_rows(episodes, design.endpoint_budgets)], ignore_index=True)
    ext = []
    for k, e in inputs_of(inputs, ExtractionValidation):
        seed = 0  # one run each: paired by draw
        ext.append(
            (
                {
                    "arm": k.which,
                    "draw": SHARED_DRAW if k.which == "pt" else k.draw,
                    "seed": seed,
                    "budget": 0,
                },
                e,
            )
        )
    episodes_ext = _episodes(workspace, ext) if ext else pd.DataFrame(columns=episodes.columns)
    budgets = sorted(b for b in episodes["budget"].unique() if b != ENDPOINT)
    # every budget of the endpoint, not only the final one: a declared secondary ("a faster start, not a
    # better end") reads the first budget against the last
    comparisons = [
        c
        for budget in (ENDPOINT, *sorted(set(design.endpoint_budgets) | {design.final_budget}))
        for arm, baseline in compared_pairs(design)
        if (c := _compare(episodes, arm, baseline, budget, design.n_boot)) is not None
    ]
    means = endpoints(episodes, design.arms, design.n_boot)
    curves = {
        arm: success_curve(episodes, arm, budgets=[int(b) for b in budgets], n_boot=design.n_boot)
        for arm in design.arms
        if arm in set(episodes["arm"])
    }
    convergence = _convergence(workspace, inputs, design)
    goals = episodes.groupby("task")["goal"].nunique()
    by_arm = _final_checkpoints(workspace, tests, design.final_budget)
    preconditions = []  # a study of fine-tuning forms only (no γ) has none
    if design.draws:
        preconditions = _preconditions(workspace, inputs, design, episodes_ext, comparisons, convergence)
    return StudyReport(
        design=design,
        gate=_gate_verdict(design, preconditions),
        goals_per_task=int(goals.min()),
        tasks=sorted(goals.index),
        preconditions=preconditions,
        comparisons=comparisons,
        curves=curves,
        selections={k.name: sel for k, sel in inputs_of(inputs, Selection)},
        convergence=convergence,
        heldout_loss=_heldout_loss(workspace, inputs, compared_pairs(design)),
        merge_errors=_merge_errors(workspace, inputs),
        endpoints=means,
        rank_spread=rank_spreads(episodes, design.variants, means, design.n_boot),
        per_task={
            arm: {task: 100 * float(v) for task, v in rows.groupby("task")["success"].mean().items()}
            for arm, rows in episodes[episodes["budget"] == ENDPOINT].groupby("arm")
        },
        per_task_intervals=_per_task_intervals(episodes),
        run_curves={
            arm: [
                RunPoint(draw=int(d), seed=int(s), budget=int(b), success=100 * float(v))
                for (d, s, b), v in rows.groupby(["draw", "seed", "budget"])["success"].mean().items()
            ]
            for arm, rows in episodes[episodes["budget"] != ENDPOINT].groupby("arm")
            if arm in curves
        },
        final_checkpoints={arm: sorted(ids) for arm, ids in sorted(by_arm.items())},
        designs_for_5_points={
            f"{c.arm}-{c.baseline}": smallest_design(
                _separable(c.components),
                n_tasks=c.n_tasks,
                at_least=(max(c.n_draws, 1), c.n_seeds, c.n_goals // max(c.n_tasks, 1)),
            )
            for c in comparisons
            if c.budget == ENDPOINT and c.arm in ("capvector", "aux", "sft_from_ao")
        },
    )


def _final_checkpoints(
    workspace: Workspace, tests: list[tuple[dict[str, Any], str]], final_budget: int
) -> dict[str, list[str]]:
    """Arm -> the checkpoints its final test evaluations ran."""
    final = {e for k, e in tests if k["budget"] == final_budget}
    by_arm: dict[str, list[str]] = {}
    for scores in read_scores(workspace.api, evaluations=sorted(final)):
        arm = next(k["arm"] for k, e in tests if e == scores.evaluation_id)
        by_arm.setdefault(arm, []).append(scores.checkpoint_id)
    return by_arm


def _merge_errors(workspace: Workspace, inputs: dict[str, str]) -> dict[str, MergeError]:
    by_arm: dict[str, list[float]] = {}
    for k, m in inputs_of(inputs, DownstreamLoss):
        error = merge_error(workspace, m)
        if error is not None:
            by_arm.setdefault(k.arm, []).append(error)
    out = {}
    for arm, errors in sorted(by_arm.items()):
        values, n = np.array(errors), len(errors)
        half = t_quantile(0.975, n - 1) * float(values.std(ddof=1)) / math.sqrt(n) if n > 1 else math.nan
        mean = float(values.mean())
        out[arm] = MergeError(mean=mean, ci_low=mean - half, ci_high=mean + half, n_runs=len(values))
    return out


def _heldout_loss(
    workspace: Workspace, inputs: dict[str, str], compared: tuple[tuple[str, str], ...]
) -> list[LossComparison]:
    losses = {
        (k.arm, k.draw, k.seed): measured_loss(workspace, m) for k, m in inputs_of(inputs, DownstreamLoss)
    }
    out = []
    for arm, baseline in compared:
        pairs = []
        for (a, d, s), value in losses.items():
            if a != arm:
                continue
            base = losses.get((baseline, d, s), losses.get((baseline, SHARED_DRAW, s)))
            if base is not None:
                pairs.append((value, base))
        if len(pairs) < 2:
            continue
        diffs = np.array([a - b for a, b in pairs])
        half = t_quantile(0.975, len(diffs) - 1) * diffs.std(ddof=1) / math.sqrt(len(diffs))
        out.append(
            LossComparison(
                arm=arm,
                baseline=baseline,
                difference=float(diffs.mean()),
                ci_low=float(diffs.mean() - half),
                ci_high=float(diffs.mean() + half),
                n_pairs=len(diffs),
                arm_mean=float(np.mean([a for a, _ in pairs])),
                baseline_mean=float(np.mean([b for _, b in pairs])),
            )
        )
    return out


def _gate_verdict(design: StudyDesign, preconditions: list[Precondition]) -> str | None:
    """At the gate stage: why CapVector's arms will not run, or None when (c) and (c′) are shown."""
    if design.stage != "gate":
        return None
    failed = [p for p in preconditions if p.key in GATING and p.holds is not True]
    if not failed:
        return None
    reasons = "; ".join(
        f"({p.key.replace('_prime', '′')}) {p.claim}: {'contradicted' if p.holds is False else 'not shown'} "
        f"— {p.detail}"
        for p in failed
    )
    return (
        "The question is untestable on this testbed: CapVector can only carry an auxiliary objective's "
        "benefit "
        f"that exists and transfers from θ_ao, and the gate did not show that. {reasons}"
    )


def _separable(components: VarianceComponents) -> VarianceComponents:
    """Components a small study could not separate (NaN) counted as 0: a design sized from them is a
    lower bound."""
    values = components.model_dump()
    return components.model_copy(update={k: 0.0 for k, v in values.items() if math.isnan(v)})


def _analyse_study(call: StepCall) -> str:
    report = analyse(call.workspace, call.inputs, call.config)
    record = call.workspace.api.register_json(
        report.model_dump(mode="json"),
        kind=STUDY_KIND,
        name=call.step,
        config={"design": call.config.model_dump(mode="json"), "cache_key": call.key},
        parents=list({a: (a, name.split("/")[0]) for name, a in sorted(call.inputs.items())}.values()),
        **provenance(),
    )
    return record.id


ANALYSE_STUDY = StepKind("analyse_study", StudyDesign, (), _analyse_study)
run_analyse_study = ANALYSE_STUDY.run
analyse_study_task = step_task(ANALYSE_STUDY)
