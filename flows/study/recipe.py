"""The recipe run once (`capvector run`) as the smallest study: the study engine plans, runs and reports it.

A pipeline preset sets one value of everything a study chooses: α (`alpha`), λ (the `orthogonal`
section), the extraction and downstream learning rates and the auxiliary weight. As a study it is one
γ draw (the extraction seed), the preset's training seeds, no gate, no tuning seeds (nothing is chosen:
every grid holds the preset's one value, flows/study/config.py), and the final budget alone. Its arms
are the preset's: sft, aux, capvector and meta_sft as study arms, the adapter forms of CapVector
(`capvector_lora`, ...) as study arms from θ_meta, and the adapter forms of SFT (`sft_lora`, ...) as
study variants at `adapter_lr`. What one draw and one seed cannot estimate (the draw component, an
interval over seeds), the study's report says it did not measure.

The preset's α × λ sweep (`capvector sweep`) is a study too (`sweep_study`): the same γ (the one draw,
the preset's extraction values given), then the `sweep` grid's cells of `sweep.arm` at the tuning seed
seeds[0], chosen on validation goals by the study's own α × λ selection; it ends there (study.sweep_arm):
which α and λ is its whole question, so no arm is compared or tested. On a home where `capvector run`
ran, its demos, θ_pt, θ_ft, θ_ao and γ are the run's (same steps, cached).
"""

from __future__ import annotations

from typing import Any

from capvector.flows.recipe.config import ARMS, PipelineConfig
from capvector.flows.study.config import StudyConfig

STUDY_ARMS = ("sft", "aux", "capvector", "meta_sft", "capvector_lora", "capvector_lora_sp")
STUDY_ARMS += ("capvector_adalora",)
"""The pipeline's arms that are study arms as they are; the others (sft_lora, ...) become variants."""


def recipe_study(cfg: PipelineConfig) -> StudyConfig:
    """The study that runs `cfg`'s recipe once (see the module); refused, naming the arm, where a run
    has nothing to compare against."""
    if "sft" not in cfg.arms:
        raise ValueError(f"arms {list(cfg.arms)}: a run compares every arm against sft; add sft to arms")
    settings = cfg.model_dump(mode="json", exclude={"alpha", "sweep", "arms"})
    lrs = [cfg.adapter_lr or cfg.downstream.lr]
    variants: dict[str, Any] = {arm: {"arm": arm, "lrs": lrs} for arm in cfg.arms if arm not in STUDY_ARMS}
    assert all(ARMS[v["arm"]].init == "pretrained" for v in variants.values())
    settings["study"] = {
        "draws": [cfg.extraction.seed],
        "tuning_seeds": [],
        "extraction_lrs": [cfg.extraction.lr],
        "extraction_aux_weights": [cfg.aux.weight],
        "aux_weights": [cfg.aux.weight],
        "alphas": [cfg.alpha],
        "budgets": [],
        "arms": [arm for arm in cfg.arms if arm in STUDY_ARMS],
        "variants": variants,
        "gate": False,
    }
    return StudyConfig.model_validate(settings)


def sweep_study(cfg: PipelineConfig) -> StudyConfig:
    """The study that runs `cfg`'s α × λ sweep (see the module): the grid `sweep.alphas` × the sweep's λ
    (both λ lists empty: the `orthogonal` section's one λ; none where the arm has no orthogonal loss)."""
    settings = cfg.model_dump(mode="json", exclude={"alpha", "sweep", "arms"})
    sweep = cfg.sweep
    orthogonal = ARMS[sweep.arm].orthogonal
    settings["study"] = {
        "sweep_arm": sweep.arm,
        "draws": [cfg.extraction.seed],
        "tuning_seeds": [cfg.seeds[0]],
        "extraction_lrs": [cfg.extraction.lr],
        "extraction_aux_weights": [cfg.aux.weight],
        "alphas": list(sweep.alphas),
        "lambdas_relative": list(sweep.lambdas_relative) if orthogonal else [],
        "lambdas_absolute": list(sweep.lambdas_absolute) if orthogonal else [],
        "budgets": [],
        "arms": [],
        "gate": False,
    }
    return StudyConfig.model_validate(settings)
