"""The study's statistics on synthetic studies whose truth is known.

Episodes are Bernoulli draws around p = goal difficulty + arm effect + per-draw and per-run offsets
(uniform, so no p leaves [0, 1] and the true difference is exactly `delta`). CapVector depends on the
γ draw; SFT, draw-independent, is broadcast over draws (draw == SHARED_DRAW) or, in the per-draw
variant, is a second draw-dependent arm.
"""

import math

import numpy as np
import pandas as pd
import pytest

from capvector.stats.paired_differences import (
    ENDPOINT,
    SHARED_DRAW,
    VarianceComponents,
    design_mdd,
    endpoint_rows,
    estimate_variance_components,
    minimum_detectable_difference,
    paired_difference,
    smallest_design,
    success_curve,
    t_quantile,
)

BUDGET = 1000


def _uniform(rng: np.random.Generator, sd: float, size) -> np.ndarray:
    return rng.uniform(-math.sqrt(3) * sd, math.sqrt(3) * sd, size)


def _frame(arm: str, success: np.ndarray, draws, n_tasks: int, per_task: int, budget: int = BUDGET):
    g, s, k = np.meshgrid(draws, np.arange(success.shape[1]), np.arange(n_tasks * per_task), indexing="ij")
    return pd.DataFrame(
        {
            "arm": arm,
            "draw": g.ravel(),
            "seed": s.ravel(),
            "task": np.array([f"task-{i}" for i in range(n_tasks)])[k.ravel() // per_task],
            "goal": 1000 + k.ravel() % per_task,
            "budget": budget,
            "success": success.ravel(),
        }
    )


def _study(
    rng: np.random.Generator,
    draws: int = 3,
    seeds: int = 3,
    tasks: int = 4,
    per_task: int = 25,
    delta: float = 0.05,
    sd_draw: float = 0.03,
    sd_seed: float = 0.05,
    sd_goal: float = 0.02,
    shared: bool = True,
) -> tuple[pd.DataFrame, float]:
    """A study's episodes, and the mean Bernoulli variance p(1 − p) of its cells."""
    k = tasks * per_task
    base = rng.uniform(0.5, 0.75, k)
    p_cap = base + delta + _uniform(rng, sd_goal, k) + _uniform(rng, sd_draw, (draws, 1, 1))
    p_cap = p_cap + _uniform(rng, sd_seed, (draws, seeds, 1))
    if shared:
        p_sft = (base + _uniform(rng, sd_seed, (seeds, 1)))[None]
    else:
        p_sft = base + _uniform(rng, sd_seed, (draws, seeds, 1))
    frames = [
        _frame("capvector", rng.random(p_cap.shape) < p_cap, np.arange(draws), tasks, per_task),
        _frame(
            "sft",
            rng.random(p_sft.shape) < p_sft,
            [SHARED_DRAW] if shared else np.arange(draws),
            tasks,
            per_task,
        ),
    ]
    bernoulli = float(np.mean([np.mean(p * (1 - p)) for p in (p_cap, p_sft)]))
    return pd.concat(frames, ignore_index=True), bernoulli


def _true_components(bernoulli: float, shared: bool, sd_draw=0.03, sd_seed=0.05, sd_goal=0.02):
    pts = 100**2
    if shared:  # SFT's run and its episodes are shared by all draws
        return VarianceComponents(
            draw=sd_draw**2 * pts,
            seed=sd_seed**2 * pts,
            run=sd_seed**2 * pts,
            goal=sd_goal**2 * pts,
            seed_goal=bernoulli * pts,
            episode=bernoulli * pts,
        )
    return VarianceComponents(
        draw=sd_draw**2 * pts, run=2 * sd_seed**2 * pts, goal=sd_goal**2 * pts, episode=2 * bernoulli * pts
    )


# ---------------------------------------------------------------- calibration on known truths


@pytest.mark.parametrize(("shared", "delta"), [(True, 0.05), (False, 0.0)])
def test_ci_covers_the_true_difference_about_95_percent_and_se_matches_the_truth(shared, delta):
    rng = np.random.default_rng(17 if shared else 18)
    covered, estimates, ses, berns = [], [], [], []
    for i in range(200):
        episodes, bernoulli = _study(rng, delta=delta, shared=shared)
        c = paired_difference(episodes, "capvector", "sft", BUDGET, n_boot=200, seed=i)
        covered.append(c.ci_low <= 100 * delta <= c.ci_high)
        estimates.append(c.difference)
        ses.append(c.se)
        berns.append(bernoulli)
    coverage = float(np.mean(covered))
    print(f"shared={shared} delta={delta}: coverage {coverage:.3f}")
    assert 0.88 <= coverage <= 0.995  # conservative by design (see _RUN_DF_CAP), never far too wide
    assert abs(np.mean(estimates) - 100 * delta) < 3 * np.std(estimates) / math.sqrt(len(estimates))
    truth = math.sqrt(_true_components(float(np.mean(berns)), shared).variance_of_mean(3, 3, 100))
    assert np.std(estimates) == pytest.approx(truth, rel=0.15)  # the variance model is the right one
    assert np.mean(ses) == pytest.approx(truth, rel=0.2)  # and the bootstrap estimates it


def test_a_null_effect_has_a_ci_around_zero_and_a_big_effect_excludes_it():
    rng = np.random.default_rng(3)
    null, _ = _study(rng, delta=0.0, per_task=50)
    c = paired_difference(null, "capvector", "sft", BUDGET)
    assert c.ci_low < 0 < c.ci_high
    big, _ = _study(rng, delta=0.2, draws=5, seeds=5, sd_draw=0.01, sd_seed=0.01, per_task=50)
    c = paired_difference(big, "capvector", "sft", BUDGET)
    assert 10 < c.ci_low < 20 < c.ci_high < 30


def test_the_cases_bootstrap_misweights_the_levels():
    """Resampling raw cases at every level counts episode noise repeatedly (too wide), and takes a
    broadcast arm's runs for new ones in every draw (too narrow); the residual bootstrap does neither."""
    rng = np.random.default_rng(4)
    episodes, bernoulli = _study(rng, sd_draw=0.0, sd_seed=0.0, sd_goal=0.0, per_task=50, shared=False)
    truth = math.sqrt(_true_components(bernoulli, False, 0, 0, 0).variance_of_mean(3, 3, 200))
    residual = paired_difference(episodes, "capvector", "sft", BUDGET, small_sample=False)
    cases = paired_difference(episodes, "capvector", "sft", BUDGET, method="cases", small_sample=False)
    assert residual.se == pytest.approx(truth, rel=0.2)
    assert cases.se > 1.4 * residual.se
    # all the variance is SFT's: seed 0 always succeeds, seed 1 never, seed 2 like CapVector's runs
    pattern = np.arange(60) % 2 == 0
    sft = np.stack([np.ones(60, bool), np.zeros(60, bool), pattern])[None]
    cap = np.broadcast_to(pattern, (4, 3, 60))
    episodes = pd.concat(
        [_frame("sft", sft, [SHARED_DRAW], 3, 20), _frame("capvector", cap, range(4), 3, 20)]
    )
    residual = paired_difference(episodes, "capvector", "sft", BUDGET, small_sample=False)
    cases = paired_difference(episodes, "capvector", "sft", BUDGET, method="cases", small_sample=False)
    assert residual.se == pytest.approx(100 * math.sqrt(0.25 / 3), rel=0.15)  # SFT's 3 runs: var/S
    assert cases.se < 0.7 * residual.se  # as if there were 4 × 3 independent SFT runs


# ---------------------------------------------------------------- pairing


def test_a_shared_arm_pairs_with_every_draw_at_the_same_seed_and_goal():
    rng = np.random.default_rng(5)
    sft = rng.random((1, 3, 40)) < 0.5  # seed- and goal-specific outcomes
    cap = np.repeat(sft, 4, axis=0).copy()  # every draw reproduces SFT run by run, goal by goal
    cap[2, 1, :4] = ~cap[2, 1, :4]  # draw 2, seed 1 differs on four goals
    changed = float(cap[2, 1, :4].sum() - sft[0, 1, :4].sum())
    episodes = pd.concat(
        [_frame("sft", sft, [SHARED_DRAW], 2, 20), _frame("capvector", cap, [7, 8, 9, 10], 2, 20)]
    )
    shuffled = episodes.sample(frac=1.0, random_state=0)  # pairing is by labels, not by row order
    c = paired_difference(shuffled, "capvector", "sft", BUDGET, n_boot=500)
    assert c.difference == pytest.approx(100 * changed / (4 * 3 * 40))
    assert (c.arm_shared, c.baseline_shared, c.n_draws, c.n_seeds, c.n_goals) == (False, True, 4, 3, 40)
    # pairing the wrong seed or goal would leave SFT's run-to-run and goal-to-goal spread in the CI
    identical = _frame("capvector", np.repeat(sft, 4, axis=0), [7, 8, 9, 10], 2, 20)
    c = paired_difference(pd.concat([identical, episodes[episodes.arm == "sft"]]), "capvector", "sft", BUDGET)
    assert (c.difference, c.ci_low, c.ci_high, c.se) == (0.0, 0.0, 0.0, 0.0)
    rolled = _frame("capvector", np.roll(np.repeat(sft, 4, axis=0), 1, axis=2), [7, 8, 9, 10], 2, 20)
    c = paired_difference(pd.concat([rolled, episodes[episodes.arm == "sft"]]), "capvector", "sft", BUDGET)
    assert c.se > 1.0


def test_arms_that_share_a_draw_are_paired_by_draw():
    """CapVector and θ_meta without the loss come from the same γ: a draw's offset cancels between them."""
    rng = np.random.default_rng(6)
    offset = np.array([-0.3, 0.0, 0.3])[:, None, None]
    p = 0.5 + offset + np.zeros((3, 3, 60))
    a, b = rng.random(p.shape) < p + 0.1, rng.random(p.shape) < p
    episodes = pd.concat([_frame("capvector", a, [0, 1, 2], 3, 20), _frame("no_loss", b, [0, 1, 2], 3, 20)])
    paired = estimate_variance_components(episodes, "capvector", "no_loss", BUDGET)
    solo = estimate_variance_components(episodes, "capvector", None, BUDGET)
    assert solo.draw > 500  # the ±30-point offsets between draws
    assert paired.draw < 0.1 * solo.draw  # cancel in the paired difference
    assert paired.seed == paired.seed_goal == 0.0  # seeds nest in draws: no seed shared across them


# ---------------------------------------------------------------- MDD and design


def test_mdd_shrinks_as_one_over_sqrt_goals():
    rng = np.random.default_rng(8)
    mdd = {}
    for per_task in (25, 100):
        episodes, _ = _study(rng, per_task=per_task, sd_draw=0.0, sd_seed=0.0, sd_goal=0.0)
        mdd[per_task] = paired_difference(episodes, "capvector", "sft", BUDGET, small_sample=False).mdd
    assert mdd[25] / mdd[100] == pytest.approx(2.0, rel=0.2)
    c = VarianceComponents(episode=2100.0, seed_goal=2100.0)
    few, many = (design_mdd(c, 3, 3, per_task, 4, small_sample=False) for per_task in (25, 100))
    assert few / many == pytest.approx(2.0)


def test_design_mdd_reproduces_the_bootstrap_mdd_of_the_same_design():
    rng = np.random.default_rng(9)
    for shared in (True, False):
        episodes, _ = _study(rng, draws=4, seeds=3, tasks=5, per_task=30, shared=shared)
        c = paired_difference(episodes, "capvector", "sft", BUDGET, n_boot=3000)
        components = estimate_variance_components(episodes, "capvector", "sft", BUDGET)
        assert components == c.components
        # the design's MDD is the expected one; this study's interval also lifts a run-level mean
        # square that came out below its goal-level floor, so it may be a little wider
        assert design_mdd(components, 4, 3, 30, 5) == pytest.approx(c.mdd, rel=0.15)
        assert minimum_detectable_difference(c.se, c.df) == pytest.approx(c.mdd)


def test_design_mdd_predicts_a_bigger_design_from_a_pilot():
    """Components from a small pilot, scaled up, match the spread the bigger design really has."""
    rng = np.random.default_rng(10)
    pilot = [estimate_variance_components(_study(rng)[0], "capvector", "sft", BUDGET) for _ in range(30)]
    mean = VarianceComponents(
        **{f: float(np.mean([getattr(p, f) for p in pilot])) for f in VarianceComponents.model_fields}
    )
    big = [
        paired_difference(
            _study(rng, draws=6, seeds=5, per_task=50)[0], "capvector", "sft", BUDGET, n_boot=100
        ).difference
        for _ in range(60)
    ]
    predicted = math.sqrt(mean.variance_of_mean(6, 5, 200))
    assert np.std(big) == pytest.approx(predicted, rel=0.3)


def test_a_broadcast_baseline_needs_seeds_not_draws():
    """SFT's seed variance is shared by every draw: more draws cannot bring its term below seed/S."""
    c = VarianceComponents(draw=9, seed=25, run=25, seed_goal=2100, episode=2100)
    assert design_mdd(c, 100, 3, 100, 8, small_sample=False) > minimum_detectable_difference(
        math.sqrt(25 / 3)
    )
    assert design_mdd(c, 6, 12, 100, 8) < design_mdd(c, 12, 6, 100, 8)


def test_smallest_design_meets_the_target_at_the_least_cost():
    c = VarianceComponents(draw=9, run=25, episode=4200)
    design = smallest_design(c, 8, target_mdd=5.0, draws=range(2, 16), seeds=range(2, 9))
    assert design is not None and design.mdd <= 5.0
    runs = 2 * design.n_draws + design.n_draws * design.n_seeds  # a draw costs two extraction runs
    for g in range(2, 16):
        for s in range(2, 9):
            if 2 * g + g * s < runs:
                assert design_mdd(c, g, s, 300, 8) > 5.0  # fewer runs fail even with the most goals
    assert smallest_design(c, 8, target_mdd=0.5, draws=range(2, 4), seeds=range(2, 4)) is None
    assert design_mdd(c, 1, 10, 100, 8) == math.inf  # one draw cannot estimate the draw variance


def test_small_samples_widen_the_interval():
    episodes, _ = _study(np.random.default_rng(11), sd_draw=0.08)
    t = paired_difference(episodes, "capvector", "sft", BUDGET)
    z = paired_difference(episodes, "capvector", "sft", BUDGET, small_sample=False)
    assert t.df < 10 and math.isinf(z.df)
    assert t.ci_high - t.ci_low > 1.2 * (z.ci_high - z.ci_low)
    assert t.difference == z.difference and t.mdd > z.mdd


def test_t_quantile_matches_tables():
    for q, df, want in [
        (0.975, 1, 12.706),
        (0.975, 2, 4.303),
        (0.975, 5, 2.571),
        (0.8, 10, 0.879),
        (0.025, 30, -2.042),
    ]:
        assert t_quantile(q, df) == pytest.approx(want, abs=2e-3)
    assert t_quantile(0.975, math.inf) == pytest.approx(1.95996, abs=1e-4)


# ---------------------------------------------------------------- curves


def test_success_curve_follows_the_budgets_with_bands():
    rng = np.random.default_rng(12)
    frames = []
    for budget, p in ((250, 0.3), (500, 0.6), (1000, 0.8)):
        frames.append(_frame("capvector", rng.random((3, 3, 100)) < p, [0, 1, 2], 4, 25, budget))
        frames.append(_frame("sft", rng.random((1, 3, 100)) < p - 0.1, [SHARED_DRAW], 4, 25, budget))
    episodes = pd.concat(frames)
    curve = success_curve(episodes, "capvector", n_boot=500)
    assert [pt.budget for pt in curve] == [250, 500, 1000]
    for pt, p in zip(curve, (30, 60, 80), strict=True):
        assert pt.ci_low < pt.mean < pt.ci_high and pt.ci_low < p < pt.ci_high
        assert pt.mean == pytest.approx(
            100 * episodes[(episodes.arm == "capvector") & (episodes.budget == pt.budget)].success.mean()
        )
    sft = success_curve(episodes, "sft", budgets=[1000], n_boot=500)
    assert (sft[0].n_draws, sft[0].n_seeds, sft[0].n_goals) == (0, 3, 100)


# ---------------------------------------------------------------- bad input


@pytest.fixture
def episodes() -> pd.DataFrame:
    return _study(np.random.default_rng(13), per_task=5)[0]


def test_missing_column_is_named(episodes):
    with pytest.raises(ValueError, match="'goal'"):
        paired_difference(episodes.drop(columns="goal"), "capvector", "sft", BUDGET)
    with pytest.raises(ValueError, match="'budget'"):
        success_curve(episodes.drop(columns="budget"), "capvector")


def test_absent_arm_and_budget_are_named(episodes):
    with pytest.raises(ValueError, match="'lora'.*not in the episodes"):
        paired_difference(episodes, "lora", "sft", BUDGET)
    with pytest.raises(ValueError, match="'lora'"):
        success_curve(episodes, "lora")
    later = episodes[episodes.arm == "capvector"].assign(budget=2000)
    with pytest.raises(ValueError, match="'sft' has no episodes at budget 2000"):
        paired_difference(pd.concat([episodes, later]), "capvector", "sft", 2000)


def test_goals_that_differ_between_arms_are_refused(episodes):
    moved = episodes.copy()
    moved.loc[moved.arm == "sft", "goal"] += 1
    with pytest.raises(ValueError, match="goals .* differ between arms 'capvector' and 'sft'"):
        paired_difference(moved, "capvector", "sft", BUDGET)


def test_seeds_and_draws_that_differ_are_refused(episodes):
    reseeded = episodes.copy()
    reseeded.loc[reseeded.arm == "sft", "seed"] += 10
    with pytest.raises(ValueError, match="seeds differ between arms"):
        paired_difference(reseeded, "capvector", "sft", BUDGET)
    redrawn = episodes.copy()
    redrawn.loc[redrawn.arm == "sft", "draw"] = 5
    redrawn = pd.concat([redrawn[redrawn.arm == "capvector"], redrawn[redrawn.arm == "sft"]])
    with pytest.raises(ValueError, match="draws differ"):
        paired_difference(redrawn, "capvector", "sft", BUDGET)


def test_incomplete_or_duplicated_runs_are_refused(episodes):
    one_run = episodes.index[(episodes.arm == "capvector") & (episodes.draw == 1) & (episodes.seed == 2)]
    with pytest.raises(ValueError, match="'capvector'.*no episode.*draw 1, seed 2"):
        paired_difference(episodes.drop(one_run[:1]), "capvector", "sft", BUDGET)
    twice = pd.concat([episodes, episodes[episodes.arm == "sft"].head(1)])
    with pytest.raises(ValueError, match="'sft'.*duplicate"):
        paired_difference(twice, "capvector", "sft", BUDGET)


def test_bad_success_values_and_mixed_draws_are_refused(episodes):
    bad = episodes.astype({"success": float})
    bad.loc[bad.index[0], "success"] = 1.5  # a fraction is an endpoint mean; above 1 is nothing
    with pytest.raises(ValueError, match="'success'"):
        paired_difference(bad, "capvector", "sft", BUDGET)
    mixed = episodes.copy()
    mixed.loc[(mixed.arm == "capvector") & (mixed.draw == 0), "draw"] = SHARED_DRAW
    with pytest.raises(ValueError, match="'capvector' mixes the shared draw"):
        paired_difference(mixed, "capvector", "sft", BUDGET)
    with pytest.raises(ValueError, match="both 'sft'"):
        paired_difference(episodes, "sft", "sft", BUDGET)


def test_one_draw_leaves_components_unestimated_and_design_asks_for_them(episodes):
    one = episodes[episodes.draw.isin([0, SHARED_DRAW])]
    c = paired_difference(one, "capvector", "sft", BUDGET, n_boot=200)
    assert set(c.unestimated) == {"draw", "run", "draw_goal", "episode"}
    with pytest.raises(ValueError, match="draw, run, draw_goal, episode"):
        design_mdd(c.components, 4, 3, 50, 4)


def test_intervals_stay_within_what_rates_and_differences_can_be():
    """Two draws × two seeds with huge run-to-run noise: t quantiles at ~1 df stretch far; the reported
    interval is clipped to ±100 points (a difference) and [0, 100] (a rate), and flagged when df < 2."""
    rng = np.random.default_rng(3)
    frames = []
    for arm, draws in (("capvector", [0, 1]), ("sft", [SHARED_DRAW])):
        runs = rng.random((len(draws), 2, 1)) < 0.5  # each run all-or-nothing
        frames.append(_frame(arm, np.broadcast_to(runs, (len(draws), 2, 10)).astype(float), draws, 1, 10))
    episodes = pd.concat(frames, ignore_index=True)
    c = paired_difference(episodes, "capvector", "sft", BUDGET, n_boot=200)
    assert -100 <= c.ci_low <= c.difference <= c.ci_high <= 100
    curve = success_curve(episodes, "capvector", n_boot=200)
    assert all(0 <= p.ci_low <= p.mean <= p.ci_high <= 100 for p in curve)
    assert c.df < 2  # 2 seeds against a shared arm: the seed variance has 1 df, whatever the data
    assert not c.reliable and "too few seeds or draws" in c.summary()


def test_a_comparison_without_variance_is_untestable():
    same = np.ones((2, 2, 10))
    episodes = pd.concat(
        [_frame("capvector", same, [0, 1], 1, 10), _frame("sft", same[:1], [SHARED_DRAW], 1, 10)],
        ignore_index=True,
    )
    c = paired_difference(episodes, "capvector", "sft", BUDGET, n_boot=200)
    assert not c.testable and "untestable" in c.summary()


def test_sizing_never_recommends_less_than_two_by_two_nor_less_than_was_run():
    tiny = VarianceComponents(draw=0.1, run=0.1, episode=1.0)  # any design meets 5 points
    assert smallest_design(tiny, 3, draws=range(1, 5), seeds=range(1, 5)).n_draws >= 2
    design = smallest_design(tiny, 3, at_least=(3, 4, 30))
    assert (design.n_draws, design.n_seeds) == (3, 4) and design.n_goals_per_task >= 30


def test_endpoint_rows_average_each_goal_over_the_budgets():
    early = _frame("sft", np.zeros((1, 2, 4)), [SHARED_DRAW], 1, 4, budget=10)
    late = _frame("sft", np.ones((1, 2, 4)), [SHARED_DRAW], 1, 4, budget=20)
    rows = endpoint_rows(pd.concat([early, late], ignore_index=True), [10, 20])
    assert (rows["budget"] == ENDPOINT).all() and (rows["success"] == 0.5).all() and len(rows) == 8
    with pytest.raises(ValueError, match="lacks test episodes"):
        endpoint_rows(early, [10, 20])


# ---------------------------------------------------------------- small designs say so (issue 41)


def test_two_seeds_against_a_shared_arm_are_never_presented_as_readable():
    """With 2 seeds the seed variance has 1 df: whatever the data, the interval gets df ≤ 1 (t₁, wide) and
    is flagged, instead of narrowing when that 1-df mean square comes out small by chance."""
    rng = np.random.default_rng(41)
    for _ in range(20):
        episodes, _ = _study(rng, draws=3, seeds=2, sd_seed=0.08)
        c = paired_difference(episodes, "capvector", "sft", BUDGET)
        assert c.df <= 1 and not c.reliable
        assert c.ci_high - c.ci_low >= 2 * 12.7 * c.se * 0.999 or c.ci_low == -100 or c.ci_high == 100
    episodes, _ = _study(rng, draws=3, seeds=3)
    assert paired_difference(episodes, "capvector", "sft", BUDGET).reliable  # 3 seeds and 3 draws: 2 df each


def test_the_old_bootstrap_narrows_where_the_presented_interval_does_not():
    """The case the residual bootstrap got wrong: the seeds' mean square small by chance at 2 seeds."""
    rng = np.random.default_rng(7)
    narrow = []
    for _ in range(40):
        episodes, _ = _study(rng, draws=3, seeds=2, sd_seed=0.1, sd_draw=0.0)
        old = paired_difference(episodes, "capvector", "sft", BUDGET, n_boot=300, method="residual")
        new = paired_difference(episodes, "capvector", "sft", BUDGET)
        if old.reliable:
            narrow.append((old.ci_high - old.ci_low) / (new.ci_high - new.ci_low))
    assert narrow and max(narrow) < 1  # every old "readable" interval was narrower than the honest one


def test_a_run_level_mean_square_is_never_taken_below_its_goal_level_floor():
    """Runs that agree exactly (no run-to-run spread in the data) still carry their goals' Bernoulli
    noise / k: the interval's variance is at least that, not 0."""
    rng = np.random.default_rng(11)
    goals = rng.random((1, 1, 90)) < 0.5
    a = np.broadcast_to(goals, (3, 3, 90))
    b = np.roll(a, 1, axis=2)  # per-goal differences, identical in every run
    episodes = pd.concat([_frame("capvector", a, [0, 1, 2], 3, 30), _frame("sft", b, [0, 1, 2], 3, 30)])
    c = paired_difference(episodes, "capvector", "sft", BUDGET)
    assert c.se > 0 and c.testable
    assert c.cluster_high - c.cluster_low == 0  # the run means alone see no spread at all


def test_the_run_level_cross_check_counts_its_units():
    rng = np.random.default_rng(12)
    nested, _ = _study(rng, draws=4, seeds=3, shared=False)
    assert paired_difference(nested, "capvector", "sft", BUDGET).cluster_df == pytest.approx(3, abs=1e-9)
    crossed, _ = _study(rng, draws=4, seeds=3)
    df = paired_difference(crossed, "capvector", "sft", BUDGET).cluster_df
    assert 2 <= df <= 5  # Satterthwaite over draws (3 df) and seeds (2 df)
