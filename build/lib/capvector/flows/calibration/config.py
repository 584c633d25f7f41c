"""The `calibrate` flow's configuration: what a study shares with it, and the calibration's design.

Its sections carry the pipeline's names and meaning (`splits.pretrain`, `data`, `policy`, `pretrain`,
`downstream`, `extraction`, `seeds`, `evaluation`), so a calibration and a study with the same settings
make the same demonstration sets and θ_pt, which the content cache then gives both. Its own parts are
the candidate tasks, the written rule that chooses among them (`rule`) and the ladder of extraction
budgets (`extraction.start_steps` .. `extraction.max_steps`). A preset is a calibration when it has a
`rule` section (`load_calibration`).
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator

from capvector.core.evaluation.rollouts import EvalConfig
from capvector.core.policies import L1ChunkConfig
from capvector.core.policies.base import AnyPolicyConfig
from capvector.core.simulation.demos import UNIT_SEEDS, DemoConfig
from capvector.core.simulation.metaworld_tasks import validate_task_names
from capvector.core.training.trainer import TrainConfig
from capvector.flows.recipe.config import DataSettings, EvalSettings, PipelineConfig, Splits, read_preset
from capvector.flows.recipe.overrides import apply_overrides
from capvector.tasks.steps.calibration import TaskRule, ladder
from capvector.tasks.steps.training import TrainStepConfig


class CalibrationSplits(BaseModel):
    """The tasks of a calibration: θ_pt's, and the candidates the rule chooses the study's sets from."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    pretrain: list[str] = Field(
        description="Meta-World tasks of D_pt, the pretraining demonstrations θ_pt is trained on (the "
        "study's splits.pretrain: the same θ_pt comes from the cache)"
    )
    candidates: list[str] = Field(
        description="tasks outside pretraining the study's extraction and downstream sets are chosen "
        "from; pilot SFT is trained on all of them together (data.episodes_downstream demos each)"
    )

    @model_validator(mode="after")
    def _valid_and_disjoint(self) -> CalibrationSplits:
        validate_task_names(self.pretrain)
        validate_task_names(self.candidates)
        overlap = sorted(set(self.pretrain) & set(self.candidates))
        if overlap:
            raise ValueError(f"splits.candidates shares task(s) {overlap} with splits.pretrain")
        return self


class ExtractionCalibration(TrainConfig):
    """θ_ft's training on the chosen D_ext (the study's `extraction` settings, as a study's θ_ft runs:
    no auxiliary objective, kept at half and three quarters), made at a ladder of budgets, each its own
    run from θ_pt: `start_steps`, doubling, up to `max_steps`. The calibration stops at the first whose
    held-out action loss moved less than `tolerance` over its second half."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    steps: None = Field(  # type: ignore[assignment]
        None,
        description="not set here: each run's length is a budget of the ladder; the calibration reports "
        "the study's extraction.steps",
    )
    start_steps: int = Field(gt=0, description="the ladder's first budget (steps of the first θ_ft run)")
    max_steps: int = Field(
        gt=0,
        description="the cap: budgets double from start_steps up to this one (the last clipped to it); "
        "a run this long that is still not flat is reported as not converged",
    )
    tolerance: float = Field(
        0.05,
        gt=0,
        lt=1,
        description="converged when the held-out action loss moved less than this fraction of its value "
        "at half the run over the second half (the study's study.flat_tolerance, precondition a)",
    )
    heldout_episodes: int = Field(
        5,
        ge=1,
        description="held-out D_ext demonstrations per task, from seeds after the training set's (the "
        "study's study.heldout_episodes: the same held-out set)",
    )

    @model_validator(mode="after")
    def _warmup(self) -> ExtractionCalibration:  # replaces TrainConfig's check, which reads `steps`
        if self.snapshot_steps:
            raise ValueError("extraction.snapshot_steps: not set here (each run keeps its half and 3/4)")
        if self.aux is not None:
            raise ValueError("extraction.aux: θ_ft's runs have no auxiliary objective")
        if self.start_steps > self.max_steps:
            raise ValueError(
                f"extraction.start_steps ({self.start_steps}) is above the cap, extraction.max_steps "
                f"({self.max_steps})"
            )
        if self.warmup_steps >= self.start_steps // 2:
            raise ValueError(
                f"extraction.warmup_steps ({self.warmup_steps}) must be below half of start_steps "
                f"({self.start_steps}): the first run's loss is read at its half"
            )
        return self

    def budgets(self) -> list[int]:
        return ladder(self.start_steps, self.max_steps)

    def run(self, steps: int) -> TrainConfig:
        """The TrainConfig of the run of `steps` steps, kept at half and three quarters (the study's
        extraction snapshots: its convergence check reads them)."""
        own = {"steps", "start_steps", "max_steps", "tolerance", "heldout_episodes"}
        snapshots = sorted({s for s in (steps // 2, (3 * steps) // 4) if 0 < s < steps})
        return TrainConfig.model_validate(
            {**self.model_dump(exclude=own), "steps": steps, "snapshot_steps": snapshots}
        )


_EVAL = EvalSettings.model_fields


class ValidationSettings(BaseModel):
    """How pilot checkpoints are tested: on validation goals only (never a test goal)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    validation_episodes_per_task: int = _EVAL["validation_episodes_per_task"]
    horizon: int = _EVAL["horizon"]
    execute_steps: int = _EVAL["execute_steps"]
    batch_size: int = _EVAL["batch_size"]


class CalibrateConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    name: str = Field("calibrate", description="the calibration's label (reports, Prefect run names)")
    splits: CalibrationSplits = Field(description="θ_pt's tasks and the candidate tasks")
    data: DataSettings = Field(
        DataSettings(),
        description="the expert demonstrations, as the study records them: episodes_pretrain for D_pt, "
        "episodes_downstream per candidate (pilot SFT), episodes_extraction for the chosen D_ext",
    )
    policy: AnyPolicyConfig = Field(L1ChunkConfig(), description="the policy's type and architecture")
    pretrain: TrainConfig = Field(description="training of θ_pt on D_pt, from scratch (the study's)")
    downstream: TrainConfig = Field(
        description="pilot SFT from θ_pt on every candidate together, once per seed (the study's "
        "downstream settings); its steps are rule.budgets' last, its snapshot_steps the others"
    )
    extraction: ExtractionCalibration = Field(
        description="θ_ft's runs on the chosen D_ext at a ladder of budgets (held-out loss convergence)"
    )
    seeds: list[int] = Field(
        default_factory=lambda: [0, 1],
        min_length=1,
        description="pilot seeds: one SFT run per seed; the rule reads their mean and their spread",
    )
    evaluation: ValidationSettings = Field(
        ValidationSettings(), description="how the pilot runs are tested (validation goals only)"
    )
    rule: TaskRule = Field(description="the written rule that chooses the study's tasks")

    @model_validator(mode="after")
    def _consistent(self) -> CalibrateConfig:
        if len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"seeds must be distinct, got {self.seeds}")
        if self.rule.budgets[-1] != self.downstream.steps:
            raise ValueError(
                f"rule.budgets end at {self.rule.budgets[-1]}, downstream.steps is {self.downstream.steps}: "
                "the pilot run's last budget is its length"
            )
        if self.downstream.snapshot_steps:
            raise ValueError("downstream.snapshot_steps: not set here (the pilot keeps rule.budgets)")
        self.pilot()  # the pipeline's own checks (obs modes, transform, image size)
        return self

    # ------------------------------------------------------------ the pipeline's view
    def _view(self, extraction: list[str], downstream: list[str], extraction_steps: int) -> PipelineConfig:
        """A pipeline config with these settings: its step configs are the ones a study with the same
        settings makes, hence the same cache keys."""
        return PipelineConfig(
            name=self.name,
            splits=Splits(pretrain=self.splits.pretrain, extraction=extraction, downstream=downstream),
            data=self.data,
            policy=self.policy,
            pretrain=self.pretrain,
            extraction=self.extraction.run(extraction_steps),
            downstream=self.downstream,
            seeds=self.seeds,
            evaluation=EvalSettings(**self.evaluation.model_dump()),
        )

    def pilot(self) -> PipelineConfig:
        """The pilot's view: the candidates as D_down (D_ext, unused there, stands in as D_pt's tasks)."""
        return self._view(self.splits.pretrain, self.splits.candidates, self.extraction.start_steps)

    def chosen(self, extraction: list[str], downstream: list[str], steps: int) -> PipelineConfig:
        """The view of a study on the chosen sets with `steps`-step extraction runs."""
        return self._view(extraction, downstream, steps)

    # ------------------------------------------------------------ step configs
    def sft_step(self, seed: int) -> TrainStepConfig:
        """Pilot SFT of one seed, kept at every budget of the rule (the study's downstream SFT run)."""
        step = self.pilot().downstream_step("sft", seed)
        train = step.train.model_copy(update={"snapshot_steps": self.rule.budgets[:-1]})
        return step.model_copy(update={"train": train})

    def validation(self) -> EvalConfig:
        return self.pilot().eval_config(validation=True)

    def extraction_demos(self, extraction: list[str], downstream: list[str]) -> tuple[DemoConfig, DemoConfig]:
        """D_ext's training demonstrations and held-out ones (seeds after the training set's), as the
        study records them (capvector.flows.study.config: heldout_demo_config)."""
        train = self.chosen(extraction, downstream, self.extraction.start_steps).demo_config("extraction")
        heldout = train.model_copy(
            update={
                "episodes_per_task": self.extraction.heldout_episodes,
                "seed_offset": train.n_units * UNIT_SEEDS,
            }
        )
        return train, heldout

    def extraction_step(self, extraction: list[str], downstream: list[str], steps: int) -> TrainStepConfig:
        """θ_ft of `steps` steps (seed extraction.seed, lr extraction.lr), kept at half and 3/4."""
        return self.chosen(extraction, downstream, steps).extraction_step(auxiliary=False)


def load_calibration(preset: str, overrides: list[str] | None = None) -> CalibrateConfig:
    """A calibration preset (it has a `rule` section) with `--set` overrides, validated."""
    data = read_preset(preset, "calibration")
    return CalibrateConfig.model_validate(apply_overrides(data, list(overrides or []), CalibrateConfig))
