"""The `study` flow's configuration: the pipeline's settings plus the experiment's design.

Everything the study decides before it runs is here, so a preset *is* the pre-registration: the grids
values are chosen from (on validation goals), the γ draws and training seeds, the declared primary
endpoint (an early downstream budget) and the curve's budgets. What the pipeline takes as given
(`alpha`, `orthogonal.weight`, `sweep`, `arms`) the study chooses or fixes itself and ignores there.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from capvector_core.demos import UNIT_SEEDS, DemoConfig
from capvector_core.evaluation import EvalConfig
from flows.config import PipelineConfig, load_config
from tasks.training import TrainStepConfig

StudyArm = Literal["sft", "aux", "meta_sft", "capvector", "null_capvector", "sft_from_ao", "sft_from_ft"]
SHARED_ARMS = ("sft", "aux")
"""Arms that start from θ_pt: one run per training seed, shared by every γ draw."""
ALL_ARMS: tuple[StudyArm, ...] = (
    "sft",
    "aux",
    "meta_sft",
    "capvector",
    "null_capvector",
    "sft_from_ao",
    "sft_from_ft",
)


class StudySettings(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    draws: list[int] = Field(default_factory=lambda: [0, 1], min_length=1)
    """Extraction seeds: each draw trains its own θ_ft, θ_ao, hence its own γ."""
    tuning_seed: int = 1000
    """Downstream (and extraction) seed of the runs values are chosen from: never a compared run's."""
    extraction_lrs: list[float] = Field(min_length=1)
    """Extraction lr grid, chosen by θ_ft's success on D_ext validation goals (draw 0's seed)."""
    heldout_episodes: int = Field(5, ge=1)
    """Held-out D_ext demonstrations per task, for the convergence check."""
    flat_tolerance: float = Field(0.05, gt=0, lt=1)
    """Converged: held-out action loss moved by less than this fraction over the second half."""
    non_inferiority_margin: float = Field(5.0, gt=0)
    """Points: θ_meta is "not worse" than θ_pt when the CI's low end is above −margin."""
    alphas: list[float] = Field(min_length=1)
    lambda_scales: list[float] = Field(min_length=1)
    """λ as multiples of ‖∇ action loss‖/‖γ‖ at θ_meta (tasks.training: orthogonal.scale)."""
    aux_weights: list[float] = Field(min_length=1)
    """The auxiliary arm's grid: as many cells as α × λ, so both get the same tuning budget."""
    primary_budget: int = Field(gt=0)
    """The declared primary endpoint: downstream steps at which the comparison is judged."""
    budgets: list[int] = Field(default_factory=list)
    """Further points of the success-vs-steps curves (the primary and final budgets are always in)."""
    arms: list[StudyArm] = Field(default_factory=lambda: list(ALL_ARMS))
    n_boot: int = Field(2000, ge=100)
    select_at: Literal["primary", "final"] = "primary"
    """Which budget's validation success a grid is chosen on (its runs keep both)."""

    @model_validator(mode="after")
    def _design(self) -> StudySettings:
        cells = len(self.alphas) * len(self.lambda_scales)
        if len(self.aux_weights) != cells:
            raise ValueError(
                f"study.aux_weights has {len(self.aux_weights)} values, the α × λ grid {cells} cells: "
                "the auxiliary arm is tuned on the same budget as CapVector"
            )
        for name in ("draws", "alphas", "lambda_scales", "aux_weights", "extraction_lrs", "budgets"):
            values = getattr(self, name)
            if len(set(values)) != len(values):
                raise ValueError(f"study.{name} has repeated values: {values}")
        if any(x <= 0 for x in self.extraction_lrs + self.lambda_scales + self.aux_weights):
            raise ValueError("study.extraction_lrs, lambda_scales and aux_weights must be positive")
        missing = {"sft", "capvector"} - set(self.arms)
        if missing:
            raise ValueError(f"study.arms must include {sorted(missing)}: every comparison is against them")
        return self


class StudyConfig(PipelineConfig):
    study: StudySettings

    @model_validator(mode="after")
    def _budgets_fit(self) -> StudyConfig:
        steps = self.downstream.steps
        bad = [b for b in [self.study.primary_budget, *self.study.budgets] if not 0 < b < steps]
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
        if self.study.tuning_seed in self.seeds or self.study.tuning_seed in self.study.draws:
            raise ValueError(f"study.tuning_seed {self.study.tuning_seed} is also a compared seed or draw")
        return self

    # ------------------------------------------------------------ derived
    @property
    def curve_budgets(self) -> list[int]:
        """Every budget a downstream run is evaluated at, the final one last."""
        return sorted({self.study.primary_budget, *self.study.budgets}) + [self.downstream.steps]

    @property
    def select_budget(self) -> int:
        return self.study.primary_budget if self.study.select_at == "primary" else self.downstream.steps

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
        self, arm: str, seed: int, lambda_scale: float | None = None, aux_weight: float | None = None
    ) -> TrainStepConfig:
        """A downstream run with the curve's snapshots; λ scaled to the action loss's gradient."""
        step = self.downstream_step(arm, seed, lambda_scale, aux_weight)
        train = step.train.model_copy(update={"snapshot_steps": self.curve_budgets[:-1]})
        update = {"train": train}
        if step.orthogonal is not None:
            update["orthogonal"] = step.orthogonal.model_copy(update={"scale": "action_gradient"})
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
