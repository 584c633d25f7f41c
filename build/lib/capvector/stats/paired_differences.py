"""Analysis of a study: paired arm differences with hierarchical-bootstrap CIs, and the design's power.

Data: one row per test episode (`COLUMNS`). An arm that does not depend on γ (SFT, auxiliary SFT)
carries `draw == SHARED_DRAW` and is broadcast: its run (seed s) on a goal pairs with the other arm's
runs (every draw g, seed s) on that goal. The estimate is the mean paired difference over draws G,
seeds S and goals K (all tasks); goals are crossed with runs (every run sees the same goals), and its
sampling variance is

    draw/G + seed/S + run/(G·S) + goal/K + draw_goal/(G·K) + seed_goal/(S·K) + episode/(G·S·K)

(`VarianceComponents`, points², estimated by method of moments and clipped at 0). A broadcast arm's
run-to-run and per-goal noise is shared by all draws: it lands in `seed` and `seed_goal`, which more
draws do not shrink. Between arms that both depend on γ, seeds nest in draws and those two are 0.

The interval the report presents ("moments", the default) is mean ± t_df · √V̂ with a conservative
method-of-moments V̂: every mean square whose expectation holds a component of the variance, each with
a positive weight (`_conservative_variance`), so no component estimated below 0 is clipped and then
dropped. V̂ over-counts the run and interaction terms a little (E V̂ ≥ V); df is Satterthwaite's over
those mean squares, so with 2 seeds and a large seed variance df is near 1 and the interval is as wide
as the data make it (benchmarks/results/interval_coverage.md). Before issue 41 the report presented
the "residual" hierarchical bootstrap: components estimated below 0 were clipped, dropped from the df
and zeroed in the resampling, so its interval narrowed exactly when a variance was worst estimated
(52 % coverage at 2 seeds where it claimed df ≥ 2). It stays, with the textbook "cases" bootstrap, for
comparison. Beside every comparison the report prints a run-level cross-check (`cluster_*`): a t
interval from the spread of run means alone (draw means and seed means), conditional on the goals.
A design that cannot estimate a component it needs (one seed against a shared arm) gets df 0 and an
interval of ±100, and says so.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable, Iterable, Sequence
from statistics import NormalDist
from typing import Any, Literal

import numpy as np
import pandas as pd
from pydantic import BaseModel, ConfigDict

COLUMNS = ("arm", "draw", "seed", "task", "goal", "budget", "success")
SHARED_DRAW = -1
"""The `draw` of an arm that does not depend on γ: one run per seed, shared by every draw."""
ENDPOINT = -1
"""The `budget` of the primary endpoint's rows: each goal's success averaged over the declared budgets
(the area under the success-vs-steps curve, normalized), so it is paired and analysed like a budget."""


def budget_name(budget: int) -> str:
    return "the endpoint (mean over budgets)" if budget == ENDPOINT else f"{budget} steps"


def endpoint_rows(episodes: pd.DataFrame, budgets: Iterable[int]) -> pd.DataFrame:
    """One `ENDPOINT` row per (arm, draw, seed, task, goal): its mean success over `budgets`, each of
    which every run must have been tested at (a missing budget would bias the mean)."""
    budgets = sorted(set(budgets))
    rows = episodes[episodes["budget"].isin(budgets)]
    keys = ["arm", "draw", "seed", "task", "goal"]
    counts = rows.groupby(keys)["budget"].nunique()
    short = counts[counts != len(budgets)]
    if len(short):
        arm, draw, seed, *_ = short.index[0]
        raise ValueError(
            f"arm {arm} (draw {draw}, seed {seed}) lacks test episodes at some of the endpoint's budgets "
            f"{budgets}"
        )
    mean = rows.groupby(keys, as_index=False)["success"].mean()
    return mean.assign(budget=ENDPOINT)[list(COLUMNS)]

Method = Literal["moments", "residual", "cases"]
_POINTS2 = 100.0**2


class VarianceComponents(BaseModel):
    """Variances (points²) of a paired difference's random effects; see the module docstring.

    draw: between γ draws. seed: between training seeds, shared by all draws (a broadcast arm's runs,
    or seeds that act alike across draws). run: a (draw, seed) run beyond both. goal: between goals
    (the goal × arm interaction), shared by all runs. draw_goal, seed_goal: per-goal effects specific to
    a draw or a seed. episode: what is left, per episode (Bernoulli noise; run × goal).
    NaN: not separable in the data (one draw or one seed); `design_mdd` asks for a value.
    """

    model_config = ConfigDict(frozen=True)

    draw: float = 0.0
    seed: float = 0.0
    run: float = 0.0
    goal: float = 0.0
    draw_goal: float = 0.0
    seed_goal: float = 0.0
    episode: float = 0.0

    def variance_of_mean(self, n_draws: int, n_seeds: int, n_goals: int) -> float:
        """Sampling variance (points²) of the mean difference over draws × seeds × goals."""
        unset = [name for name, value in self.model_dump().items() if math.isnan(value)]
        if unset:
            raise ValueError(
                f"variance component(s) {', '.join(unset)} not estimated (the pilot had one draw or one "
                f"seed); set them, e.g. components.model_copy(update={{'{unset[0]}': 9.0}})"
            )
        return sum(getattr(self, name) * w for name, w in _weights(n_draws, n_seeds, n_goals).items())


def _weights(g: int, s: int, k: int) -> dict[str, float]:
    """Each component's factor in the variance of the mean: 1 / (number of its levels)."""
    return dict(
        draw=1 / g,
        seed=1 / s,
        run=1 / (g * s),
        goal=1 / k,
        draw_goal=1 / (g * k),
        seed_goal=1 / (s * k),
        episode=1 / (g * s * k),
    )


class Comparison(BaseModel):
    """`arm` − `baseline` at one budget: mean paired difference and its bootstrap CI, in points."""

    model_config = ConfigDict(frozen=True)

    arm: str
    baseline: str
    budget: int
    difference: float
    ci_low: float
    ci_high: float
    se: float
    df: float
    """Satterthwaite df of the variance estimate (inf without the small-sample correction)."""
    cluster_low: float
    cluster_high: float
    cluster_df: float
    """The run-level cross-check: a t interval from the spread of run means (draw and seed means),
    conditional on the test goals; df 0 where there is one run per level."""
    mdd: float
    """Minimum detectable difference of this design: 80 % power, two-sided test at 1 − level."""
    arm_mean: float
    baseline_mean: float
    arm_shared: bool
    baseline_shared: bool
    """True when that arm does not depend on γ (draw == SHARED_DRAW) and was broadcast over draws."""
    n_draws: int
    """γ draws in the comparison; 0 when neither arm depends on γ."""
    n_seeds: int
    n_goals: int
    n_tasks: int
    level: float
    n_boot: int
    method: Method
    components: VarianceComponents
    unestimated: tuple[str, ...] = ()
    """Components not separable here (one draw or one seed); their variance sits in a neighbour's."""

    @property
    def testable(self) -> bool:
        """False when the two arms never differ on any goal: no variance, nothing to test."""
        return self.se > 0

    @property
    def one_draw(self) -> bool:
        """One γ draw of a γ-dependent arm: the interval is about that draw, blind to draw-to-draw spread."""
        return "draw" in self.unestimated

    @property
    def reliable(self) -> bool:
        """Readable as a statement about the method: at least 2 df, and more than one γ draw where an
        arm depends on γ. Anything else is flagged, not read."""
        return self.df >= 2 and not self.one_draw

    def summary(self) -> str:
        where = f"{self.arm} − {self.baseline} @ {budget_name(self.budget)}"
        if not self.testable:
            return f"{where}: {self.difference:+.1f} points, untestable (the arms never differ: no variance)"
        flag = (
            ""
            if self.reliable
            else "; one γ draw: about that draw only"
            if self.df >= 2
            else "; df < 2: too few seeds or draws to estimate its variance"
        )
        return (
            f"{where}: {self.difference:+.1f} points [{self.ci_low:+.1f}, {self.ci_high:+.1f}] "
            f"({100 * self.level:.0f} % CI, df {self.df:.1f}; run-level "
            f"[{self.cluster_low:+.1f}, {self.cluster_high:+.1f}], df {self.cluster_df:.0f}), "
            f"MDD {self.mdd:.1f}{flag}"
        )


class CurvePoint(BaseModel):
    """An arm's mean success (points) at one budget, with its bootstrap CI."""

    model_config = ConfigDict(frozen=True)

    budget: int
    mean: float
    ci_low: float
    ci_high: float
    n_draws: int
    n_seeds: int
    n_goals: int


class Design(BaseModel):
    """A study size and the MDD (points) it reaches."""

    model_config = ConfigDict(frozen=True)

    n_draws: int
    n_seeds: int
    n_goals_per_task: int
    n_tasks: int
    mdd: float


# ---------------------------------------------------------------- mean squares ↔ components
# Balanced ANOVA of draws (G) × seeds (S) × goals (K, nested in T fixed tasks). Mean squares: between
# draws (A), seeds (B), runs (AB), goals (C), draw × goal (AC), seed × goal (BC), residual (ABC).
# Seeds are crossed with draws only when a shared arm is broadcast (its run s serves every draw);
# between per-draw arms a seed label means nothing across draws, so seeds nest in draws: B pools into
# AB and BC into ABC, and `seed`, `seed_goal` are 0.
_MS = ("A", "B", "AB", "C", "AC", "BC", "ABC")


def _ms_df(g: int, s: int, k: int, t: int, crossed: bool) -> dict[str, int]:
    c = k - t
    if not crossed:
        return dict(A=g - 1, B=0, AB=g * (s - 1), C=c, AC=(g - 1) * c, BC=0, ABC=g * (s - 1) * c)
    return dict(
        A=g - 1, B=s - 1, AB=(g - 1) * (s - 1), C=c, AC=(g - 1) * c, BC=(s - 1) * c, ABC=(g - 1) * (s - 1) * c
    )


def _aliases(g: int, crossed: bool) -> dict[str, str]:
    """Mean squares a design lacks → the ones standing in for them, so that their component is 0.

    Nested seeds: B, BC are the pooled AB, ABC. Nested with one draw: A, AC are AB, ABC too. (Crossed
    designs need none: with one draw or seed, the missing mean squares are all 0 and cancel.)
    """
    if crossed:
        return {}
    return {"B": "AB", "BC": "ABC"} | ({"A": "AB", "AC": "ABC"} if g == 1 else {})


def _expected_ms(v: dict[str, float], g: int, s: int, k: int) -> dict[str, float]:
    """Expected mean squares of a design, given the components."""
    e = v["episode"]
    return dict(
        ABC=e,
        AC=e + s * v["draw_goal"],
        BC=e + g * v["seed_goal"],
        C=e + s * v["draw_goal"] + g * v["seed_goal"] + g * s * v["goal"],
        AB=v["run"] + e / k,
        A=v["run"] + e / k + s * (v["draw"] + v["draw_goal"] / k),
        B=v["run"] + e / k + g * (v["seed"] + v["seed_goal"] / k),
    )


def _inverse(g: int, s: int, k: int) -> dict[str, dict[str, float]]:
    """Each component as a linear combination of mean squares (method of moments)."""
    return dict(
        episode=dict(ABC=1.0),
        draw_goal=dict(AC=1 / s, ABC=-1 / s),
        seed_goal=dict(BC=1 / g, ABC=-1 / g),
        goal=dict(C=1 / (g * s), AC=-1 / (g * s), BC=-1 / (g * s), ABC=1 / (g * s)),
        run=dict(AB=1.0, ABC=-1 / k),
        draw=dict(A=1 / s, AB=-1 / s, AC=-1 / (s * k), ABC=1 / (s * k)),
        seed=dict(B=1 / g, AB=-1 / g, BC=-1 / (g * k), ABC=1 / (g * k)),
    )


def _components(ms: dict[str, float], g: int, s: int, k: int) -> dict[str, float]:
    """Method-of-moments components, clipped at 0 (mean squares with no df enter as 0)."""
    return {name: max(sum(c * ms[m] for m, c in row.items()), 0.0) for name, row in _inverse(g, s, k).items()}


def _satterthwaite(
    ms: dict[str, float], comps: dict[str, float], g: int, s: int, k: int, t: int, crossed: bool
) -> float:
    """df of Σ weight · component, a linear combination of mean squares; 0 if one it needs has no df."""
    df = _ms_df(g, s, k, t, crossed)
    coef = dict.fromkeys(_MS, 0.0)
    for name, w in _weights(g, s, k).items():
        if comps[name] > 0:  # a clipped component contributes nothing
            for m, c in _inverse(g, s, k)[name].items():
                coef[m] += w * c
    for alias, target in _aliases(g, crossed).items():
        coef[target] += coef.pop(alias)
    terms = [(coef[m] * ms[m], df[m]) for m in coef if abs(coef[m] * ms[m]) > 1e-15]
    if any(d <= 0 for _, d in terms):
        return 0.0
    spread = sum(x * x / d for x, d in terms)
    return sum(x for x, _ in terms) ** 2 / spread if spread > 0 else math.inf


_RUN_DF_CAP = 2.0
"""The interval's df is at most this multiple of its run levels' df. Satterthwaite's df over all mean
squares rises when a run-level one comes out small by chance (the goal-level ones have hundreds of
df), so that interval narrows exactly when it should not: 0.905 coverage for 3 draws × 2 seeds in
benchmarks/results/interval_coverage.md. Capped at 1× the run levels' df it was needlessly wide (0.99+
where Bernoulli noise dominates); 2× keeps every simulated design at ≥ 0.93."""
_FLOORS = {"A": "AC", "B": "BC", "AB": "ABC"}
"""A run-level mean square → the goal-level one whose 1/k it exceeds in expectation (E A ≥ E AC / k:
a run mean carries at least its goals' noise / k), so a 1-df A that came out tiny by chance is lifted."""


def _conservative_variance(
    ms: dict[str, float], g: int, s: int, k: int, t: int, crossed: bool
) -> tuple[float, float]:
    """(V̂, df): a variance of the mean with E V̂ = V + run/(gs), and no few-df mean square subtracted.

    With the expectations of `_expected_ms`: crossed, (A + B)/(gs) + (C − AC − BC)/(gsk); seeds nested
    in draws, A/(gs) + (C − AC)/(gsk), which is unbiased. The run-level mean squares A and B, which
    carry the variances that matter and have g − 1 and s − 1 df, enter with positive weights; the only
    mean squares subtracted are goal-level ones with (g − 1)(k − t) df or more, and a goal part that
    comes out below 0 counts as 0 (which only widens V̂). The exact V also subtracts AB, with
    (g − 1)(s − 1) df: clipping what that subtraction leaves is what narrowed the old interval. With
    one draw its variance cannot be seen and V̂ is conditional on that draw; with one run of a shared arm
    against several draws (θ_pt on D_ext validation) it is conditional on that run. df 0 when a mean
    square it needs has none (one seed and one draw); df at most 1 when one has 1 df.
    A run-level mean square is never taken below its goal-level floor (`_FLOORS`).
    """
    df = _ms_df(g, s, k, t, crossed)
    df |= {alias: df[target] for alias, target in _aliases(g, crossed).items()}
    run_level = 1 / (g * s)
    if crossed and s == 1 and g > 1:  # one run of the shared arm (θ_pt): conditional on it, draws vary
        terms = [("A", run_level)]
        goal_level = ("C", "AC")
    elif crossed:
        terms = [("B", run_level)] + ([("A", run_level)] if g > 1 else [])
        goal_level = ("C", "AC", "BC") if g > 1 else ("C", "BC")
    else:
        terms = [("A", run_level)] if g > 1 else [("AB", run_level)]
        goal_level = ("C", "AC")
    if df["C"] > 0 and ms["C"] > sum(ms[m] for m in goal_level[1:]):  # a goal part below 0 counts as 0
        terms += [(m, (1 if m == "C" else -1) / (g * s * k)) for m in goal_level]
    parts = []
    for m, w in terms:
        floor = _FLOORS.get(m)  # a run-level mean square below its goal-level floor is taken at the floor
        if w > 0 and floor is not None and df[floor] > 0 and ms[floor] / k > ms[m]:
            parts.append((w * ms[floor] / k, df[floor]))
        else:
            parts.append((w * ms[m], df[m]))
    variance = sum(x for x, _ in parts)
    if any(d <= 0 for x, d in parts if x):
        return variance, 0.0
    spread = sum(x * x / d for x, d in parts if x)
    satterthwaite = variance**2 / spread if spread > 0 else math.inf
    # Whether the interval is readable is the design's to say, not the data's: Satterthwaite's df rises
    # exactly when a run-level mean square comes out small by chance, and the interval then narrows and
    # misses (the old interval's failure at 2 seeds). So a run level with 1 df caps the df at 1, and
    # otherwise it stays within `_RUN_DF_CAP` × the run levels' df, however many goals there are.
    run_df = [df[m] for m, _ in terms if m in ("A", "B", "AB")]
    cap = _RUN_DF_CAP * sum(run_df) if min(run_df) >= 2 else min(run_df)
    return variance, min(satterthwaite, cap)


# ---------------------------------------------------------------- power


_THETA = np.linspace(0.0, math.pi / 2, 4001)
_LOG_COS = np.log(np.maximum(np.cos(_THETA), 1e-300))


@functools.lru_cache(maxsize=4096)
def t_quantile(q: float, df: float) -> float:
    """Student t quantile without scipy: with t = √df·tan θ the density in θ is ∝ cos(θ)^(df − 1)."""
    if not df < 1e4:
        return NormalDist().inv_cdf(q)
    if df <= 0:
        return math.copysign(math.inf, q - 0.5)
    dens = np.exp((max(df, 1.0) - 1) * _LOG_COS)
    cdf = np.concatenate([[0.0], np.cumsum(dens[1:] + dens[:-1])])
    half = float(np.interp(abs(2 * q - 1) * cdf[-1], cdf, _THETA))
    return math.copysign(math.sqrt(max(df, 1.0)) * math.tan(half), q - 0.5)


def minimum_detectable_difference(
    se: float, df: float = math.inf, level: float = 0.95, power: float = 0.8
) -> float:
    """True difference a two-sided t test at 1 − level (df degrees of freedom) detects with `power`."""
    return (t_quantile(1 - (1 - level) / 2, df) + t_quantile(power, df)) * se


def _design_variance(
    components: VarianceComponents, n_draws: int, n_seeds: int, n_goals_per_task: int, n_tasks: int
) -> tuple[float, float]:
    """(expected V̂ in points², its df) that the analysis of such a design would present."""
    v = {name: 0.0 if math.isnan(x) else x for name, x in components.model_dump().items()}
    g, s, k = n_draws, n_seeds, n_goals_per_task * n_tasks
    crossed = v["seed"] > 0 or v["seed_goal"] > 0
    df = _ms_df(g, s, k, n_tasks, crossed)
    ms = {m: x if df[m] > 0 else 0.0 for m, x in _expected_ms(v, g, s, k).items()}
    variance, dof = _conservative_variance(ms, g, s, k, n_tasks, crossed)
    if (g == 1 and (v["draw"] or v["draw_goal"])) or (s == 1 and v["seed"]):
        dof = 0.0  # the analysis could not see that variance
    return variance, dof


def design_df(
    components: VarianceComponents, n_draws: int, n_seeds: int, n_goals_per_task: int, n_tasks: int
) -> float:
    """Satterthwaite df the analysis of such a design would have (0: it cannot estimate its variance)."""
    return _design_variance(components, n_draws, n_seeds, n_goals_per_task, n_tasks)[1]


def design_mdd(
    components: VarianceComponents,
    n_draws: int,
    n_seeds: int,
    n_goals_per_task: int,
    n_tasks: int,
    level: float = 0.95,
    power: float = 0.8,
    small_sample: bool = True,
) -> float:
    """MDD (points) of a planned design, from variance components estimated on pilot data: the
    expected standard error of the interval the analysis presents (conservative, see the module
    docstring) at its expected df.

    inf when the design cannot estimate its own variance (e.g. one draw while `draw` > 0).
    """
    if min(n_draws, n_seeds, n_goals_per_task, n_tasks) < 1:
        raise ValueError("a design needs at least one draw, seed, goal per task and task")
    components.variance_of_mean(n_draws, n_seeds, n_goals_per_task * n_tasks)  # names unset components
    variance, df = _design_variance(components, n_draws, n_seeds, n_goals_per_task, n_tasks)
    return minimum_detectable_difference(math.sqrt(variance), df if small_sample else math.inf, level, power)


def _runs_then_episodes(n_draws: int, n_seeds: int, n_goals_per_task: int) -> Any:
    """(training runs, test episodes) of a per-draw arm: a γ draw costs two extraction runs."""
    return 2 * n_draws + n_draws * n_seeds, n_draws * n_seeds * n_goals_per_task


def smallest_design(
    components: VarianceComponents,
    n_tasks: int,
    target_mdd: float = 5.0,
    draws: Iterable[int] = range(2, 21),
    seeds: Iterable[int] = range(2, 21),
    goals_per_task: Iterable[int] = (10, 20, 30, 50, 75, 100, 150, 200, 300),
    cost: Callable[[int, int, int], Any] = _runs_then_episodes,
    level: float = 0.95,
    power: float = 0.8,
    small_sample: bool = True,
    at_least: tuple[int, int, int] = (2, 2, 1),
) -> Design | None:
    """Cheapest design in the grid with MDD ≤ target_mdd, or None.

    Never fewer than 2 draws and 2 seeds (a design that cannot estimate the variances it was sized
    from) nor smaller than `at_least` (draws, seeds, goals per task: the design that was run).
    cost(n_draws, n_seeds, n_goals_per_task) orders designs; the default is (training runs, episodes)
    of a per-draw arm, a draw counting its two extraction runs: runs cost far more than episodes.
    """
    best: tuple[Any, Design] | None = None
    for g, s, k in itertools.product(draws, seeds, goals_per_task):
        if g < max(2, at_least[0]) or s < max(2, at_least[1]) or k < at_least[2]:
            continue
        if best is not None and not cost(g, s, k) < best[0]:
            continue
        mdd = design_mdd(components, g, s, k, n_tasks, level, power, small_sample)
        if mdd <= target_mdd:
            best = (cost(g, s, k), Design(n_draws=g, n_seeds=s, n_goals_per_task=k, n_tasks=n_tasks, mdd=mdd))
    return None if best is None else best[1]


# ---------------------------------------------------------------- input → dense arrays


def _check_columns(episodes: pd.DataFrame) -> None:
    missing = [c for c in COLUMNS if c not in episodes.columns]
    if missing:
        raise ValueError(f"episodes lack column(s) {', '.join(map(repr, missing))} (need {COLUMNS})")


def _missing_arm(arm_column: Any, arm: str) -> None:
    arms = sorted(map(str, pd.unique(arm_column)))
    raise ValueError(f"arm {arm!r} is not in the episodes (arms: {arms})")


class _Arm:
    """One arm's episodes at one budget, checked: 0/1 successes, not mixing shared and γ draws."""

    def __init__(self, columns: dict[str, np.ndarray], name: str, budget: int):
        of_arm = columns["arm"] == name
        if not of_arm.any():
            _missing_arm(columns["arm"], name)
        rows = of_arm & (columns["budget"] == budget)
        if not rows.any():
            budgets = sorted(int(b) for b in np.unique(columns["budget"][of_arm]))
            raise ValueError(f"arm {name!r} has no episodes at budget {budget} (its budgets: {budgets})")
        try:
            self.success = columns["success"][rows].astype(float)
        except (TypeError, ValueError) as err:
            raise ValueError(f"arm {name!r}: column 'success' must be bool or 0/1 ({err})") from None
        # 0/1 per episode; an ENDPOINT row is a goal's mean over budgets, so fractions are allowed
        if not ((self.success >= 0) & (self.success <= 1)).all():
            raise ValueError(f"arm {name!r}, budget {budget}: column 'success' must lie in [0, 1] (NaN?)")
        self.name = name
        self.draw, self.seed = columns["draw"][rows].astype(int), columns["seed"][rows].astype(int)
        self.draws, self.seeds = np.unique(self.draw), np.unique(self.seed)
        self.shared = list(self.draws) == [SHARED_DRAW]
        if SHARED_DRAW in self.draws and not self.shared:
            raise ValueError(
                f"arm {name!r} mixes the shared draw {SHARED_DRAW} with γ draws "
                f"{[int(d) for d in self.draws if d != SHARED_DRAW]}"
            )
        self.task, self.goal = columns["task"][rows], columns["goal"][rows].astype(int)

    def grid(self, goal_index: np.ndarray, goals: _Goals) -> np.ndarray:
        """(draws or 1, seeds, goals) array of successes; each cell exactly once."""
        n_g, n_s, n_k = len(self.draws), len(self.seeds), len(goals)
        flat = (np.searchsorted(self.draws, self.draw) * n_s + np.searchsorted(self.seeds, self.seed)) * n_k
        flat += goal_index
        counts = np.bincount(flat, minlength=n_g * n_s * n_k).reshape(n_g, n_s, n_k)
        for bad, problem in ((counts > 1, "duplicate episodes"), (counts == 0, "no episode")):
            if bad.any():
                g, s, k = np.argwhere(bad)[0]
                where = "" if self.shared else f"draw {self.draws[g]}, "
                raise ValueError(
                    f"arm {self.name!r}: {bad.sum()} cell(s) with {problem}, e.g. {where}seed "
                    f"{self.seeds[s]}, goal {goals.label(k)}: one episode per run and goal expected"
                )
        x = np.empty(n_g * n_s * n_k)
        x[flat] = self.success
        return x.reshape(n_g, n_s, n_k)


def _same(what: str, a: str, b: str, left: Iterable, right: Iterable) -> None:
    left, right = {_plain(x) for x in left}, {_plain(x) for x in right}
    if left != right:
        only_a, only_b = sorted(left - right), sorted(right - left)
        raise ValueError(
            f"{what} differ between arms {a!r} and {b!r}: {len(only_a)} only in {a!r} {only_a[:3]}, "
            f"{len(only_b)} only in {b!r} {only_b[:3]}"
        )


def _plain(x: Any) -> Any:
    return tuple(_plain(y) for y in x) if isinstance(x, tuple) else x.item() if hasattr(x, "item") else x


class _Goals:
    """The comparison's goals, sorted by (task, goal): each goal's task index and its label."""

    def __init__(self, arms: list[_Arm]):
        task_code, self.tasks = pd.factorize(np.concatenate([a.task for a in arms]).astype(str), sort=True)
        goal = np.concatenate([a.goal for a in arms])
        low, span = goal.min(), goal.max() - goal.min() + 1
        keys, codes = np.unique(task_code * span + (goal - low), return_inverse=True)
        self.task, self.goal = keys // span, keys % span + low
        bounds = np.cumsum([0] + [len(a.success) for a in arms])
        self.index = [codes[lo:hi] for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)]

    def __len__(self) -> int:
        return len(self.task)

    def label(self, k: int) -> tuple[str, int]:
        return str(self.tasks[self.task[k]]), int(self.goal[k])

    def labels(self, codes: np.ndarray) -> set[tuple[str, int]]:
        return {self.label(k) for k in np.unique(codes)}


def _prepare(
    episodes: pd.DataFrame, names: Sequence[str], budget: int
) -> tuple[list[_Arm], list[np.ndarray], _Goals]:
    """Checked arms, their dense arrays and their (common) goals."""
    _check_columns(episodes)
    columns = {c: episodes[c].to_numpy() for c in COLUMNS}
    arms = [_Arm(columns, name, budget) for name in names]
    goals = _Goals(arms)
    first, first_goals = arms[0], np.unique(goals.index[0])
    per_draw = [a for a in arms if not a.shared]
    for arm, index in zip(arms[1:], goals.index[1:], strict=True):
        if not np.array_equal(first_goals, np.unique(index)):
            _same("goals (task, goal)", first.name, arm.name, goals.labels(first_goals), goals.labels(index))
        _same("training seeds", first.name, arm.name, first.seeds, arm.seeds)
    for arm in per_draw[1:]:
        _same("γ draws", per_draw[0].name, arm.name, per_draw[0].draws, arm.draws)
    grids = [a.grid(index, goals) for a, index in zip(arms, goals.index, strict=True)]
    return arms, grids, goals


# ---------------------------------------------------------------- estimation and bootstrap


def _rescaled(effects: np.ndarray, variance: float) -> np.ndarray:
    ms = float(np.mean(effects**2))
    if ms <= 0 or not variance > 0:
        return np.zeros_like(effects)
    return effects * math.sqrt(variance / ms)


class _Analysis:
    """Σ sign · arm on the (draw, seed, goal) grid, shared arms broadcast over draws.

    Decomposes it into the effects of the ANOVA (draw, seed, run, goal, draw × goal, seed × goal,
    residual), estimates the components from their mean squares, and bootstraps.
    """

    def __init__(self, arms: list[_Arm], grids: list[np.ndarray], goals: _Goals, signs: Sequence[int]):
        per_draw = [a for a in arms if not a.shared]
        self.n_draws = len(per_draw[0].draws) if per_draw else 0
        self.crossed = len(per_draw) < len(arms)  # a shared arm's runs serve every draw
        shape = (max(self.n_draws, 1), *grids[0].shape[1:])
        d = sum(sign * np.broadcast_to(x, shape) for x, sign in zip(grids, signs, strict=True))
        self.d = d
        g, s, k = d.shape
        task, n_t = goals.task, np.bincount(goals.task)
        t = self.n_tasks = len(n_t)
        self.mean = float(d.mean())
        run = d.mean(2)
        draw, seed = run.mean(1) - self.mean, run.mean(0) - self.mean
        run_effect = run - self.mean - draw[:, None] - seed[None, :]
        starts = np.concatenate([[0], np.cumsum(n_t)[:-1]])
        w = d - (np.add.reduceat(d, starts, axis=2) / n_t)[:, :, task]  # within run and task
        goal = w.mean((0, 1))
        draw_goal, seed_goal = w.mean(1) - goal, w.mean(0) - goal
        episode = w - goal - draw_goal[:, None, :] - seed_goal[None, :, :]
        if not self.crossed:  # seeds within draws
            run_effect, episode = run_effect + seed[None, :], episode + seed_goal[None, :, :]
            seed, seed_goal = np.zeros_like(seed), np.zeros_like(seed_goal)
        df = _ms_df(g, s, k, t, self.crossed)
        ss = dict(
            A=s * (draw**2).sum(),
            B=g * (seed**2).sum(),
            AB=(run_effect**2).sum(),
            C=g * s * (goal**2).sum(),
            AC=s * (draw_goal**2).sum(),
            BC=g * (seed_goal**2).sum(),
            ABC=(episode**2).sum(),
        )
        self.ms = {m: ss[m] / df[m] if df[m] > 0 else 0.0 for m in _MS}
        self.ms |= {alias: self.ms[target] for alias, target in _aliases(g, self.crossed).items()}
        self.comps = _components(self.ms, g, s, k)
        self.effects = {
            name: _rescaled(x, self.comps[name])
            for name, x in dict(
                draw=draw,
                seed=seed,
                run=run_effect,
                goal=goal,
                draw_goal=draw_goal,
                seed_goal=seed_goal,
                episode=episode,
            ).items()
        }
        self.goal_start, self.goal_count = starts[task], n_t[task]

    def components(self) -> VarianceComponents:
        """The estimates in points²; NaN where one draw or one seed makes levels inseparable."""
        g, s, k = self.d.shape
        out = {name: x * _POINTS2 for name, x in self.comps.items()}
        if self.n_draws == 0:  # no arm depends on γ: these levels do not exist
            out |= dict.fromkeys(("draw", "run", "draw_goal", "episode"), 0.0)
        elif g == 1:  # one draw: nothing about draws; crossed, runs are not told apart from seeds
            out |= dict.fromkeys(
                ("draw", "draw_goal") + (("run", "episode") if self.crossed else ()), math.nan
            )
        if s == 1:
            out |= dict.fromkeys(
                ("run", "episode") + (("seed", "seed_goal") if self.crossed else ()), math.nan
            )
        if k == self.n_tasks:
            out["goal"] = math.nan
        return VarianceComponents(**out)

    def df(self) -> float:
        """Satterthwaite df of the residual bootstrap (clipped components dropped; kept for comparison)."""
        g, s, k = self.d.shape
        return _satterthwaite(self.ms, self.comps, g, s, k, self.n_tasks, self.crossed)

    def moments(self) -> tuple[float, float]:
        """(V̂, df) of the mean, the interval the report presents (`_conservative_variance`)."""
        g, s, k = self.d.shape
        return _conservative_variance(self.ms, g, s, k, self.n_tasks, self.crossed)

    def cluster(self) -> tuple[float, float]:
        """(V, df) from run means alone: draw means and seed means (crossed), draw means (nested), or
        the runs of the one draw; conditional on the goals. df 0 with one level."""
        run = self.d.mean(2)
        g, s = run.shape
        if g > 1:
            parts = [(run.mean(1).var(ddof=1) / g, g - 1)]
            if self.crossed and s > 1:  # one shared run (s = 1): conditional on it
                parts.append((run.mean(0).var(ddof=1) / s, s - 1))
        else:
            parts = [(run[0].var(ddof=1) / s if s > 1 else 0.0, s - 1)]
        variance = sum(x for x, _ in parts)
        if any(d <= 0 for _, d in parts):
            return variance, 0.0
        spread = sum(x * x / d for x, d in parts)
        satterthwaite = variance**2 / spread if spread > 0 else math.inf
        fewest = min(d for _, d in parts)
        return variance, min(satterthwaite, _RUN_DF_CAP * sum(d for _, d in parts) if fewest >= 2 else fewest)

    def bootstrap(self, n_boot: int, seed: int, method: Method) -> np.ndarray:
        """Replicates of the mean: draws, seeds, seeds within each drawn draw, goals within tasks."""
        g, s, k = self.d.shape
        rng = np.random.default_rng(seed)
        gi = rng.integers(0, g, (n_boot, g))
        si = rng.integers(0, s, (n_boot, s))
        ri = rng.integers(0, s, (n_boot, g, s))
        ki = self.goal_start + (rng.random((n_boot, k)) * self.goal_count).astype(int)
        counts = np.bincount((ki + k * np.arange(n_boot)[:, None]).ravel(), minlength=n_boot * k)
        weights = counts.reshape(n_boot, k) / k  # goal weights of each replicate (rows sum to 1)
        runs = gi[:, :, None] * s + ri  # the runs drawn: seeds within each drawn draw

        def at_goals(x: np.ndarray, rows: np.ndarray) -> np.ndarray:
            """Mean of x[row, goal] over the drawn rows and drawn goals."""
            return np.take_along_axis(weights @ x.T, rows.reshape(n_boot, -1), 1).mean(1)

        if method == "cases":
            return at_goals(self.d.reshape(g * s, k), runs)
        if method != "residual":
            raise ValueError(f"unknown bootstrap method {method!r} (residual or cases)")
        e = self.effects
        out = self.mean + e["draw"][gi].mean(1) + e["seed"][si].mean(1) + weights @ e["goal"]
        out += e["run"][gi[:, :, None], ri].mean((1, 2))
        out += at_goals(e["draw_goal"], gi) + at_goals(e["seed_goal"], si)
        return out + at_goals(e["episode"].reshape(g * s, k), runs)


class _Estimate(BaseModel):
    value: float
    ci_low: float
    ci_high: float
    se: float
    df: float


def _t_interval(mean: float, variance: float, df: float, level: float) -> _Estimate:
    """mean ± t_df · √variance, in points (variance in proportion²)."""
    se = math.sqrt(max(variance, 0.0))
    half = t_quantile(1 - (1 - level) / 2, df) * se if se > 0 else 0.0
    low, high = 100 * (mean - half), 100 * (mean + half)
    return _Estimate(value=100 * mean, ci_low=low, ci_high=high, se=100 * se, df=df)


def _analyse(an: _Analysis, n_boot: int, seed: int, level: float, method: Method, small: bool) -> _Estimate:
    """The interval of `method` (points). "moments": t at the Satterthwaite df (normal without
    `small`); a bootstrap: percentile CI whose half-widths `small` stretches by t_df / z."""
    if method == "moments":
        variance, df = an.moments()
        return _t_interval(an.mean, variance, df if small else math.inf, level)
    if n_boot < 2:
        raise ValueError(f"n_boot must be at least 2, not {n_boot}")
    boot = an.bootstrap(n_boot, seed, method)
    lo, hi = np.quantile(boot, [(1 - level) / 2, 1 - (1 - level) / 2])
    df = an.df() if small else math.inf
    q = 1 - (1 - level) / 2
    stretch = t_quantile(q, df) / t_quantile(q, math.inf)
    est = an.mean
    return _Estimate(
        value=100 * est,
        ci_low=100 * (est - stretch * (est - lo)),
        ci_high=100 * (est + stretch * (hi - est)),
        se=100 * float(boot.std(ddof=1)),
        df=df,
    )


# ---------------------------------------------------------------- public analysis


def paired_difference(
    episodes: pd.DataFrame,
    arm: str,
    baseline: str,
    budget: int,
    n_boot: int = 2000,
    seed: int = 0,
    level: float = 0.95,
    method: Method = "moments",
    small_sample: bool = True,
) -> Comparison:
    """`arm` − `baseline` at `budget`, paired by (draw, seed, task, goal), with a bootstrap CI and MDD.

    A draw-independent arm (draw == SHARED_DRAW) is broadcast over the other arm's draws. Both arms
    need the same seeds (and, unless shared, draws), every run evaluated once on each of the same goals.
    """
    if arm == baseline:
        raise ValueError(f"arm and baseline are both {arm!r}")
    arms, grids, goals = _prepare(episodes, [arm, baseline], budget)
    an = _Analysis(arms, grids, goals, [1, -1])
    e = _analyse(an, n_boot, seed, level, method, small_sample)
    cluster = _t_interval(an.mean, *an.cluster(), level)
    components = an.components()
    return Comparison(
        arm=arm,
        baseline=baseline,
        budget=budget,
        difference=e.value,
        ci_low=max(e.ci_low, -100.0),  # a difference of rates lies within ±100 points
        ci_high=min(e.ci_high, 100.0),
        se=e.se,
        df=e.df,
        cluster_low=max(cluster.ci_low, -100.0),
        cluster_high=min(cluster.ci_high, 100.0),
        cluster_df=cluster.df,
        mdd=minimum_detectable_difference(e.se, e.df, level),
        arm_mean=100 * float(grids[0].mean()),
        baseline_mean=100 * float(grids[1].mean()),
        arm_shared=arms[0].shared,
        baseline_shared=arms[1].shared,
        n_draws=an.n_draws,
        n_seeds=len(arms[0].seeds),
        n_goals=len(goals),
        n_tasks=an.n_tasks,
        level=level,
        n_boot=n_boot,
        method=method,
        components=components,
        unestimated=tuple(n for n, v in components.model_dump().items() if math.isnan(v)),
    )


def estimate_variance_components(
    episodes: pd.DataFrame, arm: str, baseline: str | None, budget: int
) -> VarianceComponents:
    """Variance components (points²) of `arm` − `baseline` (or of `arm` alone), for `design_mdd`."""
    names = [arm] if baseline is None else [arm, baseline]
    arms, grids, goals = _prepare(episodes, names, budget)
    return _Analysis(arms, grids, goals, [1, -1][: len(names)]).components()


def success_curve(
    episodes: pd.DataFrame,
    arm: str,
    budgets: Iterable[int] | None = None,
    n_boot: int = 2000,
    seed: int = 0,
    level: float = 0.95,
    method: Method = "moments",
    small_sample: bool = True,
) -> list[CurvePoint]:
    """Mean success (points) of `arm` at each budget (default: all of its budgets) with bootstrap CIs."""
    _check_columns(episodes)
    if budgets is None:
        budgets = sorted(int(b) for b in episodes.loc[episodes["arm"] == arm, "budget"].unique())
        if not budgets:
            _missing_arm(episodes["arm"], arm)
    points = []
    for budget in budgets:
        arms, grids, goals = _prepare(episodes, [arm], budget)
        an = _Analysis(arms, grids, goals, [1])
        e = _analyse(an, n_boot, seed, level, method, small_sample)
        points.append(
            CurvePoint(
                budget=budget,
                mean=e.value,
                ci_low=max(e.ci_low, 0.0),  # a rate lies within [0, 100]
                ci_high=min(e.ci_high, 100.0),
                n_draws=an.n_draws,
                n_seeds=len(arms[0].seeds),
                n_goals=len(goals),
            )
        )
    return points
