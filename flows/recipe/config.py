"""The recipe's configuration, composed of the library's own config models: RecipeSettings, what every
experiment sets, and PipelineConfig, a pipeline preset (`capvector run`, `capvector sweep`), which adds the
values a run takes as given. A study's config (capvector.flows.study.config.StudyConfig) is the other
RecipeSettings.

Presets (`flows/presets/*.yaml`) are instances of them; `--set a.b=value` overrides are checked
against the model before validation (`capvector.flows.recipe.overrides`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, NonNegativeFloat, model_validator

from capvector.core.adapters.adalora import AdaLoraConfig
from capvector.core.adapters.lora import LoraConfig
from capvector.core.adapters.lora_sp import LoraSPConfig
from capvector.core.evaluation.rollouts import EvalConfig
from capvector.core.policies import L1ChunkConfig
from capvector.core.policies.base import AnyPolicyConfig
from capvector.core.simulation.demos import EVAL_SEED_BASE, VALIDATION_SEED_BASE, DemoConfig
from capvector.core.simulation.envs import CAMERAS
from capvector.core.simulation.metaworld_tasks import validate_task_names
from capvector.core.simulation.obs_transforms import ObsTransformConfig
from capvector.core.training.trainer import AuxConfig, TrainConfig
from capvector.flows.recipe.overrides import apply_overrides
from capvector.tasks.steps.training import OrthogonalSettings, TrainStepConfig
from capvector.tasks.steps.vectors import MergeConfig, VectorFilter

PRESET_DIR = Path(__file__).parent.parent / "presets"

ArmName = Literal[
    "sft",
    "aux",
    "capvector",
    "meta_sft",
    "sft_lora",
    "capvector_lora",
    "sft_lora_sp",
    "capvector_lora_sp",
    "sft_adalora",
    "capvector_adalora",
]


class Arm(BaseModel):
    """One downstream fine-tuning recipe: where it starts and what it adds to standard SFT.

    init: θ_pt, θ_meta = θ_pt + α·γ, the null control θ_pt + α·γ_null (`null_meta`, regularized with
    γ_null), a study's dose θ_pt + α_dose·γ (`dose_meta`), or one of the extraction checkpoints θ_ao
    (`auxiliary`) and θ_ft (`standard`)."""

    init: Literal["pretrained", "meta", "null_meta", "dose_meta", "auxiliary", "standard"]
    aux: bool = False
    orthogonal: bool = False
    adapter: Literal["full", "lora", "lora_sp", "adalora"] = "full"


ARMS: dict[str, Arm] = {
    "sft": Arm(init="pretrained"),
    "aux": Arm(init="pretrained", aux=True),
    "capvector": Arm(init="meta", orthogonal=True),
    "meta_sft": Arm(init="meta"),
    "sft_lora": Arm(init="pretrained", adapter="lora"),
    "capvector_lora": Arm(init="meta", orthogonal=True, adapter="lora"),
    "sft_lora_sp": Arm(init="pretrained", adapter="lora_sp"),
    "capvector_lora_sp": Arm(init="meta", orthogonal=True, adapter="lora_sp"),
    "sft_adalora": Arm(init="pretrained", adapter="adalora"),
    "capvector_adalora": Arm(init="meta", orthogonal=True, adapter="adalora"),
    # The study's controls (capvector.flows.study.plan): they need a null vector and the extraction
    # checkpoints per draw.
    "null_capvector": Arm(init="null_meta", orthogonal=True),
    "meta_sft_dose": Arm(init="dose_meta"),
    "sft_from_ao": Arm(init="auxiliary"),
    "sft_from_ft": Arm(init="standard"),
}


class Splits(BaseModel):
    """Task splits: D_down's tasks appear in neither the pretraining nor the extraction set."""

    model_config = ConfigDict(extra="forbid")
    pretrain: list[str] = Field(
        description="Meta-World tasks (e.g. reach-v3) of D_pt, the pretraining demonstrations θ_pt is "
        "trained on; more tasks: a broader base model"
    )
    extraction: list[str] = Field(
        description="tasks of D_ext, on which θ_ft (SFT) and θ_ao (SFT + aux) are trained from θ_pt; "
        "γ = θ_ao − θ_ft is extracted from them (may share tasks with pretrain)"
    )
    downstream: list[str] = Field(
        description="tasks of D_down, the fine-tuning and evaluation tasks every arm is compared on; "
        "must share no task with pretrain or extraction"
    )

    @model_validator(mode="after")
    def _valid_and_disjoint(self) -> Splits:
        for name in ("pretrain", "extraction", "downstream"):
            validate_task_names(getattr(self, name))
        seen = set(self.pretrain) | set(self.extraction)
        overlap = sorted(seen & set(self.downstream))
        if overlap:
            raise ValueError(f"splits.downstream shares task(s) {overlap} with pretrain/extraction")
        return self


class DataSettings(BaseModel):
    """The expert demonstrations (Meta-World's scripted experts) every split is recorded as."""

    model_config = ConfigDict(extra="forbid")
    obs_mode: Literal["state", "pixels"] = Field(
        "state",
        description="what the policy observes: `state` (Meta-World's 39-number observation) or `pixels` "
        "(a camera image); must equal policy.obs_mode",
    )
    camera: str = Field(
        "corner2",
        description="Meta-World camera the images are rendered from (pixels mode; topview, corner, "
        "corner2, corner3, corner4, behindGripper, gripperPOV)",
    )
    image_size: int = Field(
        64,
        description="side of the square rendered images in pixels (pixels mode); must equal "
        "policy.image_size; larger: more vision tokens, slower",
    )
    horizon: int = Field(
        500,
        ge=1,
        le=500,
        description="most environment steps per expert episode (1-500, Meta-World's limit); an episode "
        "without success within it is discarded and another seed is tried",
    )
    episodes_pretrain: int = Field(
        25, ge=1, description="successful expert episodes recorded per task of splits.pretrain"
    )
    episodes_extraction: int = Field(
        10, ge=1, description="successful expert episodes per task of splits.extraction (θ_ft, θ_ao's data)"
    )
    episodes_downstream: int = Field(
        10, ge=1, description="successful expert episodes per task of splits.downstream (the arms' data)"
    )
    workers: int = Field(
        2, ge=1, description="processes recording demonstrations in parallel; speed only, never the data"
    )
    obs_transform: ObsTransformConfig = Field(
        default_factory=ObsTransformConfig,
        description="fixed, seeded map of the state the policy sees (state mode): the policy applies it, "
        "so demos, training and evaluation share it; `random_features` hides positions the auxiliary "
        "targets carry (a positive control for the auxiliary objective)",
    )


class EvalSettings(BaseModel):
    """How checkpoints are tested: rollouts on D_down's tasks from goals no demonstration used."""

    model_config = ConfigDict(extra="forbid")
    episodes_per_task: int = Field(
        20,
        ge=1,
        description="test episodes per downstream task (each a distinct held-out goal seed); more: "
        "narrower confidence intervals, longer evaluation",
    )
    validation_episodes_per_task: int = Field(
        10,
        ge=1,
        description="episodes per task on validation goals (seeds disjoint from the test ones), on which "
        "α, λ and other values are chosen",
    )
    horizon: int = Field(
        500,
        ge=1,
        le=500,
        description="most environment steps per evaluation episode (1-500); an episode succeeds if the "
        "task reports success at any step within it",
    )
    execute_steps: int = Field(
        1,
        ge=1,
        description="actions executed from each predicted chunk before the policy is queried again "
        "(at most policy.chunk_size); larger: fewer policy calls, less closed-loop",
    )
    batch_size: int = Field(
        64,
        ge=1,
        description="environments stepped together per policy call; speed and memory only, never results",
    )
    ood_camera: str | None = Field(
        None,
        description="out-of-distribution check (pixels only): a camera no demonstration was recorded "
        "with; `capvector run` prints the `capvector evaluate` command that tests its final checkpoints "
        "through it; null: no such check",
    )
    record_video: int = Field(
        0, ge=0, description="test episodes per task recorded as mp4 videos (artifacts of kind `video`)"
    )


class LambdaGrid(BaseModel):
    """λ values tried in an α × λ grid, in either form (the names of OrthogonalSettings, as lists); both
    lists empty: the one λ of the config's `orthogonal` section, in the form it is set."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)  # NaN/inf: refused, naming the field
    lambdas_absolute: list[NonNegativeFloat] = Field(
        default_factory=list, description="λ values tried in absolute form (orthogonal.lambda_absolute)"
    )
    lambdas_relative: list[NonNegativeFloat] = Field(
        default_factory=list,
        description="λ values tried as multiples of ‖∇ action loss‖/‖γ‖ (orthogonal.lambda_relative)",
    )

    renamed: ClassVar[dict[str, str]] = {
        "lambdas": "list the λ values as lambdas_absolute",
        "lambda_scales": "list the λ values as lambdas_relative",
    }

    @model_validator(mode="before")
    @classmethod
    def _renamed(cls, data: Any) -> Any:
        for name in (n for n in cls.renamed if isinstance(data, dict) and n in data):
            raise ValueError(f"{name} was renamed: {cls.renamed[name]}")
        return data

    def lambda_cells(self, orthogonal: OrthogonalSettings) -> list[dict[str, float]]:
        """One {form: value} per λ tried, relative ones first; the section's own λ when both are empty."""
        cells = [{"lambda_relative": x} for x in self.lambdas_relative]
        cells += [{"lambda_absolute": x} for x in self.lambdas_absolute]
        return cells or [orthogonal.lam]


def lambda_label(values: dict[str, Any]) -> str:
    """How the λ of a cell (a dict holding one of the two form names) reads in step labels and reports:
    `λ_rel=0.1`, `λ_abs=0.0001`, or `λ none` for a cell without the orthogonal loss. Sweeps recorded
    before the two names existed hold an absolute `lambda`."""
    for form, short in (("lambda_relative", "rel"), ("lambda_absolute", "abs"), ("lambda", "abs")):
        if values.get(form) is not None:
            return f"λ_{short}={values[form]:g}"
    return "λ none"


class SweepSettings(LambdaGrid):
    """The α × λ grid of `capvector sweep` (a study: capvector.flows.study.recipe.sweep_study); choices
    are made on validation goals only."""

    alphas: list[float] = Field(
        default_factory=lambda: [0.5, 1.1, 1.5],
        description="merge coefficients α tried (θ_meta = θ_pt + α·γ); set the chosen one as `alpha`",
    )
    arm: ArmName = Field(
        "capvector", description="the arm whose α × λ cells are trained (on seeds[0]) and validated"
    )


class RecipeSettings(BaseModel):
    """What every experiment on the recipe sets: the splits, the demonstrations, the policy, the three
    training stages, the auxiliary objective, γ's tensors, the orthogonal loss, the adapters, the seeds and
    the evaluation. A pipeline preset (PipelineConfig) adds the values a run takes as given (`alpha`,
    `arms`, the `sweep` grid); a study (capvector.flows.study.config.StudyConfig) adds its `study` design
    instead, and refuses those three by name (extra fields are forbidden)."""

    # NaN or inf in α or a learning rate would only fail after training: refused here, naming the field
    # (the nested configs refuse them too: TrainConfig, AuxConfig, OrthogonalSettings, LoRA, LoRA-SP).
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    name: str = Field(
        "pipeline", description="the run's label (reports, Prefect run names); changes no result"
    )
    splits: Splits = Field(description="which Meta-World tasks each stage trains or is tested on")
    data: DataSettings = Field(DataSettings(), description="the expert demonstrations")
    policy: AnyPolicyConfig = Field(L1ChunkConfig(), description="the policy's type and architecture")
    pretrain: TrainConfig = Field(description="training of θ_pt on D_pt, from scratch")
    extraction: TrainConfig = Field(description="training of θ_ft and θ_ao on D_ext, from θ_pt")
    aux: AuxConfig = Field(
        AuxConfig(name="dynamics"), description="the auxiliary objective of θ_ao and of the `aux` arm"
    )
    downstream: TrainConfig = Field(description="each arm's fine-tuning on D_down")
    vector: VectorFilter = Field(VectorFilter(), description="which tensors γ covers (and θ_meta changes)")
    orthogonal: OrthogonalSettings = Field(
        OrthogonalSettings(), description="the orthogonal loss λ·Σ|γ ⊙ Δ'| of the capvector arms"
    )
    lora: LoraConfig = Field(
        LoraConfig(target_modules=["attn.*_proj", "mlp.fc*", "action_head.*"]),
        description="the adapter of the *_lora arms",
    )
    lora_sp: LoraSPConfig = Field(
        LoraSPConfig(target_modules=["attn.*_proj", "mlp.fc*", "action_head.*"], bank_size=32),
        description="the adapter of the *_lora_sp arms",
    )
    adalora: AdaLoraConfig = Field(
        AdaLoraConfig(target_modules=["attn.*_proj", "mlp.fc*", "action_head.*"]),
        description="the adapter of the *_adalora arms (peft's AdaLoRA: ranks reallocated while training)",
    )
    adapter_lr: float | None = Field(
        None,
        gt=0,
        allow_inf_nan=False,
        description="learning rate of the LoRA / LoRA-SP / AdaLoRA arms (adapters usually want several "
        "times full fine-tuning's); null: downstream.lr. Choose it on validation goals, e.g. a one-cell "
        "`sweep` with sweep.arm=sft_lora",
    )
    seeds: list[int] = Field(
        default_factory=lambda: [0],
        min_length=1,
        description="training seeds (distinct) of the downstream runs: each arm is trained once per seed, "
        "so more seeds give tighter comparisons at proportional cost",
    )
    evaluation: EvalSettings = Field(EvalSettings(), description="how checkpoints are tested")

    @model_validator(mode="after")
    def _consistent(self) -> RecipeSettings:
        if self.policy.obs_mode != self.data.obs_mode:
            raise ValueError(
                f"policy.obs_mode ({self.policy.obs_mode}) differs from data.obs_mode ({self.data.obs_mode})"
            )
        self._give_policy_the_obs_transform()
        if self.data.obs_mode == "pixels" and self.policy.image_size != self.data.image_size:
            raise ValueError(
                f"policy.image_size ({self.policy.image_size}) differs from data.image_size "
                f"({self.data.image_size})"
            )
        ood = self.evaluation.ood_camera
        if ood is not None and ood not in CAMERAS:
            raise ValueError(f"evaluation.ood_camera: unknown camera {ood!r}; Meta-World has {CAMERAS}")
        if ood is not None and (self.data.obs_mode != "pixels" or ood == self.data.camera):
            raise ValueError(
                f"evaluation.ood_camera ({ood}) needs pixels observations and a camera other than "
                f"data.camera ({self.data.camera}); obs_mode is {self.data.obs_mode}"
            )
        if len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"seeds must be distinct, got {self.seeds}")
        return self

    def _give_policy_the_obs_transform(self) -> None:
        """data.obs_transform is declared once, here; the policy (which applies it) gets a copy."""
        transform = self.data.obs_transform
        if "obs_transform" not in type(self.policy).model_fields:
            if transform.active:
                raise ValueError(
                    f"data.obs_transform {transform.kind!r}: policy type {self.policy.type!r} has no "
                    "obs_transform setting (the token-backbone policies have)"
                )
            return
        if self.policy.obs_transform == transform:
            return
        if self.policy.obs_transform.active:
            raise ValueError(
                "policy.obs_transform differs from data.obs_transform: set data.obs_transform only "
                "(the pipeline gives it to the policy)"
            )
        if transform.active and self.data.obs_mode != "state":
            raise ValueError(
                f"data.obs_transform {transform.kind!r} maps the state: data.obs_mode must be 'state', "
                f"got {self.data.obs_mode!r}"
            )
        self.policy = self.policy.model_copy(update={"obs_transform": transform})

    # ------------------------------------------------------------ step configs
    def demo_config(self, split: Literal["pretrain", "extraction", "downstream"]) -> DemoConfig:
        episodes = {
            "pretrain": self.data.episodes_pretrain,
            "extraction": self.data.episodes_extraction,
            "downstream": self.data.episodes_downstream,
        }[split]
        # Per-patch 3D targets where an objective reads them: extraction (θ_ao) and downstream (aux arm).
        depth = self.aux.name == "spatial_depth" and split != "pretrain"
        return DemoConfig(
            tasks=getattr(self.splits, split),
            episodes_per_task=episodes,
            obs_mode=self.data.obs_mode,
            camera=self.data.camera,
            image_size=self.data.image_size,
            horizon=self.data.horizon,
            workers=self.data.workers,
            **({"patch_xyz": True, "patch_grid": self.policy.grid_size} if depth else {}),
        )

    def pretrain_step(self) -> TrainStepConfig:
        return TrainStepConfig(policy=self.policy, train=self.pretrain)

    def extraction_step(self, auxiliary: bool) -> TrainStepConfig:
        train = self.extraction.model_copy(update={"aux": self.aux if auxiliary else None})
        return TrainStepConfig(train=train)

    def downstream_step(
        self, arm: str, seed: int, lam: dict[str, float] | None = None, aux_weight: float | None = None
    ) -> TrainStepConfig:
        """Arm `arm`'s run at `seed`; `lam` ({form: value}) replaces the orthogonal section's λ."""
        spec = ARMS[arm]
        aux = self.aux if aux_weight is None else self.aux.model_copy(update={"weight": aux_weight})
        update = {"seed": seed, "aux": aux if spec.aux else None}
        if spec.adapter != "full" and self.adapter_lr is not None:
            update["lr"] = self.adapter_lr
        train = self.downstream.model_copy(update=update)
        orthogonal = None
        if spec.orthogonal:
            orthogonal = self.orthogonal if lam is None else self.orthogonal.with_lambda(lam)
        return TrainStepConfig(
            train=train,
            adapter=spec.adapter,
            lora=self.lora if spec.adapter == "lora" else None,
            lora_sp=self.lora_sp if spec.adapter == "lora_sp" else None,
            adalora=self.adalora if spec.adapter == "adalora" else None,
            orthogonal=orthogonal,
        )

    def merge_config(self, alpha: float) -> MergeConfig:
        return MergeConfig(alpha=alpha, **self.vector.model_dump())

    def eval_config(self, validation: bool = False, camera: str | None = None) -> EvalConfig:
        return EvalConfig(
            tasks=self.splits.downstream,
            episodes_per_task=(
                self.evaluation.validation_episodes_per_task
                if validation
                else self.evaluation.episodes_per_task
            ),
            seed_base=VALIDATION_SEED_BASE if validation else EVAL_SEED_BASE,
            horizon=self.evaluation.horizon,
            obs_mode=self.data.obs_mode,
            camera=camera or self.data.camera,
            image_size=self.data.image_size,
            execute_steps=self.evaluation.execute_steps,
            batch_size=self.evaluation.batch_size,
            record_video=0 if validation else self.evaluation.record_video,
        )


class PipelineConfig(RecipeSettings):
    """A pipeline preset (`capvector run`, `capvector sweep`): the recipe's settings and the values a run
    takes as given, which a study chooses or fixes itself."""

    alpha: float = Field(
        1.1,
        allow_inf_nan=False,
        description="merge coefficient α: θ_meta = θ_pt + α·γ (the paper's best is 1.1; 0: no capability "
        "added); chosen on validation by `sweep`; a study chooses its own from study.alphas",
    )
    arms: list[ArmName] = Field(
        default_factory=lambda: ["sft", "aux", "capvector"],
        description="downstream recipes compared: sft (from θ_pt), aux (SFT + aux objective), capvector "
        "(from θ_meta with the orthogonal loss), meta_sft (from θ_meta, plain SFT), and the *_lora / "
        "*_lora_sp / *_adalora adapter variants; a study uses study.arms instead",
    )
    sweep: SweepSettings = Field(SweepSettings(), description="the α × λ grid of `capvector sweep`")


def preset_path(preset: str) -> Path:
    """A preset name (`smoke`, `quick`, `paper`) or a path to a YAML file."""
    path = Path(preset)
    if path.suffix in (".yaml", ".yml") and path.exists():
        return path
    candidate = PRESET_DIR / f"{preset}.yaml"
    if not candidate.exists():
        known = sorted(p.stem for p in PRESET_DIR.glob("*.yaml"))
        raise ValueError(f"unknown preset {preset!r}; known presets: {known} (or give a .yaml path)")
    return candidate


PRESET_COMMANDS = {"pipeline": "run", "study": "study", "calibration": "calibrate"}
"""The command that runs each kind of preset."""


def preset_kind(data: dict) -> str:
    """What a preset is: a `study` section makes a study, a `rule` section a calibration."""
    return "study" if "study" in data else "calibration" if "rule" in data else "pipeline"


def read_preset(preset: str, kind: str) -> dict:
    """A preset's settings, refused naming the command that runs it when it is not of `kind`."""
    path = preset_path(preset)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:  # a bad tag, indentation, an unclosed bracket: one line naming the place
        raise ValueError(f"preset {path}: {yaml_problem(e)}") from None
    if not isinstance(data, dict):
        raise ValueError(f"preset {path}: expected a mapping of settings, got a {type(data).__name__}")
    found = preset_kind(data)
    if found != kind:
        raise ValueError(
            f"preset {path} is a {found} preset, not a {kind}: run it with "
            f"`capvector {PRESET_COMMANDS[found]} --preset {preset}`"
        )
    return data


def load_config(
    preset: str = "quick", overrides: list[str] | None = None, model: type[RecipeSettings] | None = None
) -> RecipeSettings:
    """A preset with `--set` overrides, validated by `model` (PipelineConfig; a study's StudyConfig)."""
    model = model or PipelineConfig
    data = read_preset(preset, "pipeline" if model is PipelineConfig else "study")
    return model.model_validate(apply_overrides(data, list(overrides or []), model))


def yaml_problem(error: yaml.YAMLError) -> str:
    """A YAML error in one line: where (line and column, 1-based) and what, without the excerpt."""
    mark = getattr(error, "problem_mark", None)
    problem = getattr(error, "problem", None) or str(error)
    context = getattr(error, "context", None)
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    text = f"{where}{f'{context}, ' if context else ''}{problem}"
    return " ".join(text.split())
