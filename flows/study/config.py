"""The `study` flow's configuration: the recipe's settings (RecipeSettings) plus the experiment's design.

Everything the study decides before it runs is here, so a preset *is* the pre-registration: the grids
values are chosen from (on validation goals), the γ draws and training seeds, the declared primary
endpoint (an early downstream budget) and the curve's budgets. What a pipeline preset takes as given
(`alpha`, `sweep`, `arms`) the study chooses or fixes itself: a study preset that sets them is refused,
naming the field. λ's grid is `study.lambdas_relative` + `study.lambdas_absolute`, or, both empty, the
`orthogonal` section's one λ.
"""

from __future__ import annotations

from typing import Literal

from pydantic import ConfigDict, Field, NonNegativeInt, model_validator

from capvector.core.evaluation.rollouts import EvalConfig
from capvector.core.simulation.demos import UNIT_SEEDS, DemoConfig
from capvector.flows.recipe.config import ArmName, LambdaGrid, RecipeSettings, load_config
from capvector.flows.study.variants import Variant, check_variants, variant_config
from capvector.tasks.steps.training import TrainStepConfig

StudyArm = Literal[
    "sft",
    "aux",
    "meta_sft",
    "meta_sft_dose",
    "capvector",
    "null_capvector",
    "sft_from_ao",
    "sft_from_ft",
    "capvector_lora",
    "capvector_lora_sp",
    "capvector_adalora",
]
"""The adapter forms of CapVector (from θ_meta, orthogonal loss, an adapter) are arms a study may list;
their SFT forms are `study.variants` (flows/study/variants.py) and each is compared against its own."""
SHARED_ARMS = ("sft", "aux")
"""Arms that start from θ_pt: one run per training seed, shared by every γ draw."""
GATE_ARMS: tuple[StudyArm, ...] = ("sft", "aux", "sft_from_ao", "sft_from_ft")
"""Arms that test the preconditions; the others run only when the gate passes."""
ALL_ARMS: tuple[StudyArm, ...] = (  # the default arms; `meta_sft_dose` runs only where a preset asks
    "sft",
    "aux",
    "meta_sft",
    "capvector",
    "null_capvector",
    "sft_from_ao",
    "sft_from_ft",
)


class StudySettings(LambdaGrid):
    """The experiment's design, declared before it runs (a preset is its pre-registration).

    Args:
        draws: extraction seeds; each draw trains its own θ_ft and θ_ao, hence its own γ.
        draws_per_replicate: K; with K > 1 the draws form len(draws) / K replicates, each γ̄^r the mean of
            K consecutive draws' γ, and CapVector's arms (θ_meta, the orthogonal loss, the null vector)
            and SFT from θ_ao / θ_ft (the replicate's first draw's) run per replicate: the replicate is
            the analysis's unit, its variance the draw-level one. γ of one draw is mostly seed noise;
            the mean of K points at the signal with cos √(Kρ / (Kρ + 1 − ρ)).
        tuning_seeds: seeds of the runs values are chosen from (never a compared run's seed or draw);
            a cell's score is its mean validation success over them, so with 2 or more one lucky
            tuning run cannot pick a value. Empty: nothing is chosen — every grid has one value, used as
            given (the recipe run once, `capvector run`, is such a study: flows/study/recipe.py).
        tuning_vector_draws: extraction draws whose mean γ̄_tune is the vector every α × λ tuning run
            merges and regularizes with (no compared arm uses them); empty: each tuning seed's own γ
            from the extraction grid's runs. One γ is mostly seed noise: tuning λ on it tunes on noise.
        extraction_lrs: θ_ft's lr grid, chosen on D_ext validation goals (ties: lower held-out loss).
        extraction_aux_weights: θ_ao's auxiliary-weight grid, chosen on D_ext validation goals (ties:
            lower held-out action loss): γ comes from the strongest objective the extraction set
            supports, not from the downstream arm's choice.
        heldout_episodes: held-out D_ext demonstrations per task (convergence and tie-breaks).
        flat_tolerance: converged when the held-out action loss moved less than this fraction over the
            second half of the extraction run.
        non_inferiority_margin: points; θ_meta is "not worse" than θ_pt when the CI's low end is above
            −margin.
        alphas: merge coefficients of the α × λ grid (default 0.5–2: the paper's best was 1.1); one value
            fixes α and tunes λ alone.
        dose_alpha: the merge coefficient of the `meta_sft_dose` arm (θ_pt + dose_alpha·γ, plain SFT):
            beside θ_meta at the chosen α it separates "too little signal" from "not additive".
        lambdas_relative: λ as multiples of ‖∇ action loss‖/‖γ‖ at θ_meta (orthogonal.lambda_relative);
            put 0 (θ_meta without the loss) in the grid, so the loss has to earn its place.
        lambdas_absolute: λ in the paper's absolute form (orthogonal.lambda_absolute; its best was
            1e-4): the α × λ grid is alphas × (lambdas_relative + lambdas_absolute), or alphas × the
            `orthogonal` section's λ when both are empty.
        aux_weights: the downstream auxiliary arm's grid: as many cells as α × λ, so both arms get the
            same tuning budget.
        budgets: downstream steps at which every run is kept and tested besides the final one. The
            primary endpoint is the mean success over these budgets and the final one (the area under
            the success-vs-steps curve); values are chosen on validation goals at that same endpoint.
            Empty: the final budget alone.
        arms: the compared arms (sft and capvector are required, except in a gate-only study: with
            `gate: true` and exactly the gate's arms, the study ends at its gate whatever it shows, and
            its report is the gate's).
        n_boot: bootstrap resamples per interval.
        gate: run the arms that test the preconditions (SFT, auxiliary SFT, SFT from θ_ao and from θ_ft)
            first and the CapVector arms only when (c) and (c′) hold with intervals above 0; otherwise the
            report says the question is untestable on this testbed.
        variants: named arms from θ_pt with config overrides (`set`, the `--set` syntax) and their own lr
            grid, each chosen on validation goals at the tuning seeds; shared arms like `sft`, compared
            against it (flows/study/variants.py). A study of `sft` and variants only needs no γ: it runs
            no extraction stage and no gate.
        sft_lrs: full fine-tuning's lr grid, chosen like a variant's; empty: `downstream.lr`.
        compare: declared (arm, baseline) pairs among the variants (and sft) compared besides each
            variant against sft, e.g. `[[lora_sp_b64, lora_r64]]` (paired by seed and goal).
        sweep_arm: set, the study is an α × λ sweep of this arm (`capvector sweep`, flows/study/recipe.py)
            and ends at its selection: the arm's α × λ cells, trained at the tuning seeds on the γ of the
            one draw (extraction values given: one each) and chosen on validation goals; nothing is
            compared, tested or analysed (arms, variants and the other grids stay empty, gate false).
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    variants: dict[str, Variant] = Field(default_factory=dict)
    sft_lrs: list[float] = Field(default_factory=list)
    compare: list[tuple[str, str]] = Field(default_factory=list)
    draws: list[NonNegativeInt] = Field(default_factory=lambda: [0, 1], min_length=1)
    draws_per_replicate: int = Field(1, ge=1)
    tuning_seeds: list[int] = Field(default_factory=lambda: [1000, 1001])
    tuning_vector_draws: list[NonNegativeInt] = Field(default_factory=list)
    extraction_lrs: list[float] = Field(default_factory=list)
    extraction_aux_weights: list[float] = Field(default_factory=list)
    heldout_episodes: int = Field(5, ge=1)
    flat_tolerance: float = Field(0.05, gt=0, lt=1)
    non_inferiority_margin: float = Field(5.0, gt=0)
    alphas: list[float] = Field(default_factory=lambda: [0.5, 1.0, 1.5, 2.0], min_length=1)
    dose_alpha: float | None = Field(None, gt=0)
    aux_weights: list[float] = Field(default_factory=list)
    budgets: list[int]
    arms: list[StudyArm] = Field(default_factory=lambda: list(ALL_ARMS))
    n_boot: int = Field(2000, ge=100)
    gate: bool = True
    sweep_arm: ArmName | None = None

    @property
    def needs_gamma(self) -> bool:
        """Whether an arm depends on γ (anything but `sft`, `aux` and the variants, all from θ_pt): only
        then do the extraction stage, the γ draws and the gate run. A sweep always merges γ."""
        return self.sweep_arm is not None or any(arm not in SHARED_ARMS for arm in self.arms)

    @property
    def chooses(self) -> bool:
        """Whether values are chosen on validation goals (tuning runs, `select` steps); without tuning
        seeds every grid holds the one value used."""
        return bool(self.tuning_seeds)

    @property
    def gate_only(self) -> bool:
        """A study of the preconditions alone: it ends at its gate, passed or not."""
        return self.gate and set(self.arms) == set(GATE_ARMS)

    def _grids_and_arms(self) -> None:
        """Every grid has distinct (and, for lrs and weights, positive) values; `sft` is an arm."""
        grids = ("draws", "tuning_seeds", "tuning_vector_draws", "alphas", "lambdas_relative", "sft_lrs")
        grids += ("lambdas_absolute", "aux_weights", "extraction_lrs", "extraction_aux_weights", "budgets")
        for name in grids:
            values = getattr(self, name)
            if len(set(values)) != len(values):
                raise ValueError(f"study.{name} has repeated values: {values}")
        positive = ("extraction_lrs", "aux_weights", "extraction_aux_weights", "sft_lrs")
        bad = [name for name in positive if any(x <= 0 for x in getattr(self, name))]
        if bad:
            raise ValueError(f"study.{', study.'.join(bad)} must be positive")
        if "sft" not in self.arms and self.sweep_arm is None:
            raise ValueError("study.arms must include sft: every comparison is against it")
        twice = sorted({arm for arm in self.arms if self.arms.count(arm) > 1})
        if twice:
            raise ValueError(f"study.arms lists {', '.join(twice)} more than once: each arm is run once")
        unknown = sorted({x for pair in self.compare for x in pair} - {*self.variants, "sft"})
        if unknown:
            raise ValueError(f"study.compare names {unknown}: only study.variants and sft are compared there")
        if any(arm == baseline for arm, baseline in self.compare):
            raise ValueError(f"study.compare pairs an arm with itself: {self.compare}")
        clash = sorted(set(self.variants) & set(ALL_ARMS + ("meta_sft_dose",)))
        if clash:
            raise ValueError(f"study.variants {clash} are named like a study arm: give them names of theirs")

    def _given_values(self) -> None:
        """Without tuning seeds nothing is chosen: each grid holds at most one value, the one used."""
        if self.chooses:
            return
        grids = ("extraction_lrs", "extraction_aux_weights", "aux_weights", "alphas", "sft_lrs")
        wide = [f"study.{name}" for name in grids if len(getattr(self, name)) > 1]
        wide += [f"study.variants.{n}.lrs" for n, v in self.variants.items() if len(v.lrs) > 1]
        if len(self.lambdas_relative) + len(self.lambdas_absolute) > 1:
            wide.append("study.lambdas_relative + study.lambdas_absolute")
        if wide:
            raise ValueError(
                f"study.tuning_seeds is empty (nothing is chosen) but {', '.join(wide)} hold several values: "
                "give one value each, or tuning seeds to choose among them"
            )
        if self.tuning_vector_draws:
            raise ValueError("study.tuning_vector_draws need study.tuning_seeds: they are tuning's vector")

    def _sweep(self) -> None:
        """A sweep chooses α × λ alone, on the γ of one draw: every other value is given, nothing compared."""
        if not self.tuning_seeds:
            raise ValueError("study.sweep_arm needs study.tuning_seeds: the seeds of its α × λ runs")
        if len(self.draws) != 1:
            raise ValueError(f"study.sweep_arm: a sweep tunes on one γ, study.draws lists {self.draws}")
        given = ("extraction_lrs", "extraction_aux_weights")
        wide = [f"study.{name}" for name in given if len(getattr(self, name)) != 1]
        if wide:
            raise ValueError(f"study.sweep_arm: {', '.join(wide)} must hold one value each, used as given")
        unused = ("arms", "variants", "sft_lrs", "compare", "aux_weights", "tuning_vector_draws", "gate")
        unused = [f"study.{name}" for name in unused if getattr(self, name)]
        unused += ["study.dose_alpha"] if self.dose_alpha is not None else []
        if unused:
            raise ValueError(
                f"study.sweep_arm: a sweep compares nothing and ends at its α × λ selection, but "
                f"{', '.join(unused)} {'is' if len(unused) == 1 else 'are'} set: leave them empty "
                "(gate false)"
            )

    @model_validator(mode="after")
    def _design(self) -> StudySettings:
        self._grids_and_arms()
        self._given_values()
        if self.sweep_arm is not None:
            self._sweep()
            return self
        if not self.needs_gamma:
            if self.gate:
                raise ValueError(
                    f"study.gate is true but study.arms {self.arms} need no γ: the gate tests preconditions "
                    "of γ's arms; set study.gate: false"
                )
            if not self.variants and self.chooses:
                raise ValueError("study.arms need no γ and study.variants is empty: nothing to compare")
            if "aux" in self.arms and not self.aux_weights:
                raise ValueError("study.aux_weights is empty: the aux arm's weight is chosen from it")
            return self
        for name in ("extraction_lrs", "extraction_aux_weights", "aux_weights"):
            if not getattr(self, name):
                raise ValueError(f"study.{name} is empty: a study with γ's arms chooses from it")
        cells = len(self.alphas) * max(1, len(self.lambdas_relative) + len(self.lambdas_absolute))
        if len(self.aux_weights) != cells:
            raise ValueError(
                f"study.aux_weights has {len(self.aux_weights)} values, the α × λ grid {cells} cells: "
                "the auxiliary arm is tuned on the same budget as CapVector"
            )
        if len(self.draws) % self.draws_per_replicate:
            raise ValueError(
                f"study.draws ({len(self.draws)}) must split into replicates of study.draws_per_replicate "
                f"({self.draws_per_replicate}) draws"
            )
        if ("meta_sft_dose" in self.arms) != (self.dose_alpha is not None):
            raise ValueError("study.dose_alpha and the arm meta_sft_dose go together: set both or neither")
        shared = sorted(set(self.tuning_vector_draws) & set(self.draws))
        if shared:
            raise ValueError(f"study.tuning_vector_draws {shared} are also compared draws")
        # a gate-only study has no CapVector arm, nor need a recipe run once (nothing chosen) have one
        given = self.gate_only or not self.chooses
        missing = {"sft", "capvector"} - set(self.arms) - ({"capvector"} if given else set())
        if missing:
            raise ValueError(
                f"study.arms must include {sorted(missing)}: every comparison is against them (a study of "
                "fine-tuning forms lists sft and study.variants only; a gate-only study lists exactly the "
                f"gate's arms {list(GATE_ARMS)} with study.gate: true)"
            )
        if self.gate:
            lacking = sorted(set(GATE_ARMS) - set(self.arms))
            if lacking:
                raise ValueError(f"study.gate needs arms {lacking}: they test preconditions c and c′")
        return self


class StudyConfig(RecipeSettings):
    study: StudySettings

    @model_validator(mode="after")
    def _budgets_fit(self) -> StudyConfig:
        steps = self.downstream.steps
        bad = [b for b in self.study.budgets if not 0 < b < steps]
        if bad:
            raise ValueError(
                f"study budgets {bad} must lie strictly between 0 and downstream.steps ({steps}), "
                "which is the final budget"
            )
        if self.extraction.steps < 4:
            raise ValueError(
                f"extraction.steps ({self.extraction.steps}) must be at least 4: the convergence check "
                "reads the held-out loss at half and three quarters of the run"
            )
        check_variants(self.study.variants, self.model_dump(mode="json"))
        if self.study.sweep_arm is not None:
            return self  # a sweep compares no seed or draw: its tuning seeds may be any
        compared = set(self.seeds) | (set(self.study.draws) if self.study.needs_gamma else set())
        clash = sorted(set(self.study.tuning_seeds) & compared)
        if clash:
            raise ValueError(f"study.tuning_seeds {clash} are also compared seeds or draws")
        return self

    # ------------------------------------------------------------ derived
    @property
    def curve_budgets(self) -> list[int]:
        """Every budget a downstream run is kept and evaluated at, the final one last; the primary
        endpoint is the mean success over them."""
        return sorted(self.study.budgets) + [self.downstream.steps]

    @property
    def extraction_snapshots(self) -> list[int]:
        """Half and three quarters of the extraction run: the held-out loss's flatness is read there."""
        steps = self.extraction.steps
        return sorted({s for s in (steps // 2, (3 * steps) // 4) if 0 < s < steps})

    def heldout_demo_config(self) -> DemoConfig:
        """More D_ext demonstrations, from seeds after the training set's."""
        train = self.demo_config("extraction")
        return train.model_copy(
            update={
                "episodes_per_task": self.study.heldout_episodes,
                "seed_offset": train.n_units * UNIT_SEEDS,
            }
        )

    def downstream_heldout_demo_config(self) -> DemoConfig:
        """Held-out D_down demonstrations (seeds after the training set's): the secondary endpoint,
        every compared run's held-out action loss."""
        train = self.demo_config("downstream")
        return train.model_copy(
            update={
                "episodes_per_task": self.study.heldout_episodes,
                "seed_offset": train.n_units * UNIT_SEEDS,
            }
        )

    def extraction_run(
        self, auxiliary: bool, seed: int, lr: float, aux_weight: float | None = None
    ) -> TrainStepConfig:
        step = self.extraction_step(auxiliary)
        if auxiliary and aux_weight is not None:
            step = step.model_copy(
                update={
                    "train": step.train.model_copy(
                        update={"aux": self.aux.model_copy(update={"weight": aux_weight})}
                    )
                }
            )
        train = step.train.model_copy(
            update={"seed": seed, "lr": lr, "snapshot_steps": self.extraction_snapshots}
        )
        return step.model_copy(update={"train": train})

    def study_downstream(
        self,
        arm: str,
        seed: int,
        lam: dict[str, float] | None = None,
        aux_weight: float | None = None,
    ) -> TrainStepConfig:
        """A downstream run with the curve's snapshots; `lam` ({form: value}) as in `downstream_step`."""
        step = self.downstream_step(arm, seed, lam, aux_weight)
        train = step.train.model_copy(update={"snapshot_steps": self.curve_budgets[:-1]})
        return step.model_copy(update={"train": train})

    def variant_downstream(self, name: str, seed: int, lr: float) -> TrainStepConfig:
        """Variant `name`'s run at `seed` and `lr`: its arm under its overrides, with the curve's budgets."""
        variant = self.study.variants[name]
        cfg = variant_config(self.model_dump(mode="json"), name, variant)
        step = cfg.downstream_step(variant.arm, seed)
        train = step.train.model_copy(update={"lr": lr, "snapshot_steps": self.curve_budgets[:-1]})
        return step.model_copy(update={"train": train})

    def sft_downstream(self, seed: int, lr: float | None = None) -> TrainStepConfig:
        """Full fine-tuning's run at `seed`, at `lr` when a grid chose one (else `downstream.lr`)."""
        step = self.study_downstream("sft", seed)
        if lr is None:
            return step
        return step.model_copy(update={"train": step.train.model_copy(update={"lr": lr})})

    def extraction_validation(self) -> EvalConfig:
        """D_ext's validation goals: the extraction lr and preconditions (b), (d) are judged there."""
        downstream = self.eval_config(validation=True)
        return downstream.model_copy(update={"tasks": list(self.splits.extraction)})


def load_study(preset: str, overrides: list[str] | None = None) -> StudyConfig:
    """A study preset (it has a `study` section) with `--set` overrides, validated."""
    config = load_config(preset, overrides, StudyConfig)
    assert isinstance(config, StudyConfig)
    return config
