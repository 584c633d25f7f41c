"""The `study` flow's configuration: the pipeline's settings plus the experiment's design.

Everything the study decides before it runs is here, so a preset *is* the pre-registration: the grids
values are chosen from (on validation goals), the γ draws and training seeds, the declared primary
endpoint (an early downstream budget) and the curve's budgets. What the pipeline takes as given
(`alpha`, `orthogonal.weight`, `sweep`, `arms`) the study chooses or fixes itself and ignores there.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, NonNegativeInt, model_validator

from capvector.core.evaluation.rollouts import EvalConfig
from capvector.core.simulation.demos import UNIT_SEEDS, DemoConfig
from capvector.flows.recipe.config import PipelineConfig, load_config
from capvector.tasks.steps.training import TrainStepConfig

StudyArm = Literal[
    "sft", "aux", "meta_sft", "meta_sft_dose", "capvector", "null_capvector", "sft_from_ao", "sft_from_ft"
]
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


class StudySettings(BaseModel):
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
            tuning run cannot pick a value.
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
        lambda_scales: λ as multiples of ‖∇ action loss‖/‖γ‖ at θ_meta (capvector.tasks.steps.training:
        orthogonal.scale);
            0 (θ_meta without the loss) is in the default grid, so the loss has to earn its place.
        lambdas: λ in the paper's absolute form (orthogonal.scale "absolute"; its best was 1e-4), grid
            cells beside the relative ones: the α × λ grid is alphas × (lambda_scales + lambdas).
        aux_weights: the downstream auxiliary arm's grid: as many cells as α × λ, so both arms get the
            same tuning budget.
        budgets: downstream steps at which every run is kept and tested besides the final one. The
            primary endpoint is the mean success over these budgets and the final one (the area under
            the success-vs-steps curve); values are chosen on validation goals at that same endpoint.
        arms: the compared arms (sft and capvector are required).
        n_boot: bootstrap resamples per interval.
        gate: run the arms that test the preconditions (SFT, auxiliary SFT, SFT from θ_ao and from θ_ft)
            first and the CapVector arms only when (c) and (c′) hold with intervals above 0; otherwise the
            report says the question is untestable on this testbed.
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    draws: list[NonNegativeInt] = Field(default_factory=lambda: [0, 1], min_length=1)
    draws_per_replicate: int = Field(1, ge=1)
    tuning_seeds: list[int] = Field(default_factory=lambda: [1000, 1001], min_length=1)
    tuning_vector_draws: list[NonNegativeInt] = Field(default_factory=list)
    extraction_lrs: list[float] = Field(min_length=1)
    extraction_aux_weights: list[float] = Field(min_length=1)
    heldout_episodes: int = Field(5, ge=1)
    flat_tolerance: float = Field(0.05, gt=0, lt=1)
    non_inferiority_margin: float = Field(5.0, gt=0)
    alphas: list[float] = Field(default_factory=lambda: [0.5, 1.0, 1.5, 2.0], min_length=1)
    lambda_scales: list[float] = Field(default_factory=lambda: [0.0, 0.1, 1.0])
    lambdas: list[float] = Field(default_factory=lambda: [1.0e-4])
    dose_alpha: float | None = Field(None, gt=0)
    aux_weights: list[float] = Field(min_length=1)
    budgets: list[int] = Field(min_length=1)
    arms: list[StudyArm] = Field(default_factory=lambda: list(ALL_ARMS))
    n_boot: int = Field(2000, ge=100)
    gate: bool = True

    @property
    def gate_only(self) -> bool:
        """A study of the preconditions alone: it ends at its gate, passed or not (issue 39's powered
        gate, backported from main to this pinned checkout)."""
        return self.gate and set(self.arms) == set(GATE_ARMS)

    @model_validator(mode="after")
    def _design(self) -> StudySettings:
        cells = len(self.alphas) * (len(self.lambda_scales) + len(self.lambdas))
        if not self.lambda_scales and not self.lambdas:
            raise ValueError("study.lambda_scales and study.lambdas are both empty: the grid needs a λ")
        if len(self.aux_weights) != cells:
            raise ValueError(
                f"study.aux_weights has {len(self.aux_weights)} values, the α × λ grid {cells} cells: "
                "the auxiliary arm is tuned on the same budget as CapVector"
            )
        grids = ("draws", "tuning_seeds", "tuning_vector_draws", "alphas", "lambda_scales", "lambdas")
        grids += ("aux_weights",)
        grids += ("extraction_lrs",)
        grids += ("extraction_aux_weights",)
        for name in (*grids, "budgets"):
            values = getattr(self, name)
            if len(set(values)) != len(values):
                raise ValueError(f"study.{name} has repeated values: {values}")
        positive = ("extraction_lrs", "aux_weights", "extraction_aux_weights")
        bad = [name for name in positive if any(x <= 0 for x in getattr(self, name))]
        if bad:
            raise ValueError(f"study.{', study.'.join(bad)} must be positive")
        for name in ("lambda_scales", "lambdas"):  # 0 belongs in the grid: θ_meta fine-tuned without it
            if any(x < 0 for x in getattr(self, name)):
                raise ValueError(f"study.{name} must be ≥ 0, not {getattr(self, name)}")
        if len(self.draws) % self.draws_per_replicate:
            raise ValueError(
                f"study.draws ({len(self.draws)}) must split into replicates of study.draws_per_replicate "
                f"({self.draws_per_replicate}) draws"
            )
        twice = sorted({arm for arm in self.arms if self.arms.count(arm) > 1})
        if twice:
            raise ValueError(f"study.arms lists {', '.join(twice)} more than once: each arm is run once")
        if ("meta_sft_dose" in self.arms) != (self.dose_alpha is not None):
            raise ValueError("study.dose_alpha and the arm meta_sft_dose go together: set both or neither")
        shared = sorted(set(self.tuning_vector_draws) & set(self.draws))
        if shared:
            raise ValueError(f"study.tuning_vector_draws {shared} are also compared draws")
        missing = {"sft", "capvector"} - set(self.arms) - ({"capvector"} if self.gate_only else set())
        if missing:
            raise ValueError(f"study.arms must include {sorted(missing)}: every comparison is against them")
        if self.gate:
            lacking = sorted(set(GATE_ARMS) - set(self.arms))
            if lacking:
                raise ValueError(f"study.gate needs arms {lacking}: they test preconditions c and c′")
        return self


class StudyConfig(PipelineConfig):
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
        compared = set(self.seeds) | set(self.study.draws)
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
        lambda_scale: float | None = None,
        aux_weight: float | None = None,
        lambda_absolute: float | None = None,
    ) -> TrainStepConfig:
        """A downstream run with the curve's snapshots; λ scaled to the action loss's gradient
        (`lambda_scale`), or absolute as the paper's (`lambda_absolute`)."""
        if lambda_scale is not None and lambda_absolute is not None:
            raise ValueError("a run takes λ in one form: lambda_scale or lambda_absolute")
        weight = lambda_scale if lambda_absolute is None else lambda_absolute
        step = self.downstream_step(arm, seed, weight, aux_weight)
        train = step.train.model_copy(update={"snapshot_steps": self.curve_budgets[:-1]})
        update = {"train": train}
        if step.orthogonal is not None:
            scale = "absolute" if lambda_absolute is not None else "action_gradient"
            update["orthogonal"] = step.orthogonal.model_copy(update={"scale": scale})
        return step.model_copy(update=update)

    def extraction_validation(self) -> EvalConfig:
        """D_ext's validation goals: the extraction lr and preconditions (b), (d) are judged there."""
        downstream = self.eval_config(validation=True)
        return downstream.model_copy(update={"tasks": list(self.splits.extraction)})


def load_study(preset: str, overrides: list[str] | None = None) -> StudyConfig:
    """A study preset (it has a `study` section) with `--set` overrides, validated."""
    config = load_config(preset, overrides, StudyConfig)
    assert isinstance(config, StudyConfig)
    return config
