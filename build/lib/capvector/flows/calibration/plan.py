"""A calibration's plan: the study's tasks and extraction budget, measured before the study is declared
(the `calibrate` flow, capvector.flows.calibration.flow, runs it).

    demos D_pt -> θ_pt (the study's: same settings, same cache keys)
    -> demos of every candidate -> per pilot seed, SFT from θ_pt on all candidates, kept at each budget
    -> every kept checkpoint tested on validation goals (never a test goal)
    -> the written rule (capvector.flows.calibration.config: rule) per task; kept tasks ranked by SFT's mean
    and dealt
       alternately to D_down and D_ext
    -> when both sets are large enough: D_ext's demos and held-out demos (the study's), then θ_ft at
       budgets start, 2·start, ... up to the cap, each its own run, its held-out action loss read at half
       and at the end, stopping at the first whose loss moved less than the tolerance
    -> one `calibration` artifact (capvector.tasks.steps.calibration): curves, verdicts, sets, the extraction
    budget and
       its evidence, with the evaluations, runs and measurements as parents; rendered as Markdown

Every step is an existing cached step task submitted through a StepRunner, so a second calibration, or
a study with the same settings, takes what is done from the content cache; the flow blocks where a
result decides the next runs (the pilot's evaluations decide D_ext; each extraction run's losses,
whether the next budget runs).
"""

from __future__ import annotations

from typing import Any

from capvector.flows.calibration.config import CalibrateConfig
from capvector.flows.runtime.step_submission import StepRunner, resolve
from capvector.tasks.runtime.workspace import workspace_for
from capvector.tasks.steps.calibration import (
    CalibrationStepConfig,
    calibrate_task,
    calibration_markdown,
    choose_tasks,
    extraction_convergence,
    extraction_losses,
    load_calibration_doc,
    preset_lines,
)
from capvector.tasks.steps.data import collect_demos_task
from capvector.tasks.steps.evaluation import evaluate_task
from capvector.tasks.steps.held_out_loss import held_out_loss_task
from capvector.tasks.steps.training import snapshots_of, train_task


def _dump(model: Any) -> dict[str, Any]:
    return model.model_dump(mode="json")


def calibration_steps(cfg: CalibrateConfig) -> int:
    """How many steps a calibration submits at most (progress shows `k/N`): fewer when too few tasks
    pass the rule (no extraction runs) or when an extraction budget below the cap converges."""
    pilot = 3 + len(cfg.seeds) * (1 + len(cfg.rule.budgets))  # 2 demo sets, θ_pt; runs, evaluations
    extraction = 2 + 3 * len(cfg.extraction.budgets())  # D_ext, held out; per budget a run, 2 losses
    return pilot + extraction + 1  # the calibration artifact


def _step_config(cfg: CalibrateConfig) -> dict[str, Any]:
    return _dump(
        CalibrationStepConfig(
            name=cfg.name,
            candidates=cfg.splits.candidates,
            seeds=cfg.seeds,
            rule=cfg.rule,
            extraction={"budgets": cfg.extraction.budgets(), "tolerance": cfg.extraction.tolerance},
            config=_dump(cfg),
        )
    )


def plan_calibration(cfg: CalibrateConfig, steps: StepRunner) -> dict[str, Any]:
    """Submit the calibration's steps to `steps` (a flow's runner, or a CacheProbe): the calibration
    artifact's id, its Markdown, the chosen sets, the extraction budget and the study preset's lines."""
    workspace = workspace_for(steps.home)
    pilot = cfg.pilot()

    def submit(task: Any, step: str, inputs: dict[str, Any], config: Any) -> Any:
        return steps.submit(task, step, inputs, config if isinstance(config, dict) else _dump(config))

    demos_pt = submit(collect_demos_task, "demos pretrain", {}, pilot.demo_config("pretrain"))
    pretrained = submit(train_task, "pretrain θ_pt", {"data": demos_pt}, pilot.pretrain_step())
    candidates = submit(collect_demos_task, "demos candidates", {}, pilot.demo_config("downstream"))
    runs = {
        seed: submit(
            train_task, f"pilot SFT seed {seed}", {"data": candidates, "init": pretrained}, cfg.sft_step(seed)
        )
        for seed in cfg.seeds
    }
    validation = cfg.validation()  # validation goals: never a test goal
    inputs: dict[str, Any] = {}
    for seed, run in runs.items():
        for budget, checkpoint in snapshots_of(workspace, resolve(run)).items():
            inputs[f"eval/{seed}/{budget}"] = submit(
                evaluate_task,
                f"validate pilot SFT seed {seed} @ {budget}",
                {"checkpoint": checkpoint},
                validation,
            )
    inputs = {k: resolve(v) for k, v in inputs.items()}
    step_config = _step_config(cfg)
    _, _, split = choose_tasks(workspace, inputs, CalibrationStepConfig.model_validate(step_config))

    if split.enough:
        train_demos, heldout_demos = cfg.extraction_demos(split.extraction, split.downstream)
        demos_ext = submit(collect_demos_task, "demos extraction", {}, train_demos)
        heldout = submit(collect_demos_task, "demos extraction (held out)", {}, heldout_demos)
        for budget in cfg.extraction.budgets():
            run = submit(
                train_task,
                f"extraction θ_ft {budget} steps",
                {"data": demos_ext, "init": pretrained},
                cfg.extraction_step(split.extraction, split.downstream, budget),
            )
            kept = snapshots_of(workspace, resolve(run))
            inputs[f"run/{budget}"] = resolve(run)
            for where, at in (("half", budget // 2), ("end", budget)):
                inputs[f"loss/{budget}/{where}"] = submit(
                    held_out_loss_task,
                    f"held-out loss θ_ft {budget} steps @ {at}",
                    {"checkpoint": kept[at], "data": heldout},
                    {},
                )
            inputs |= {k: resolve(v) for k, v in inputs.items()}
            convergence = extraction_convergence(
                extraction_losses(workspace, inputs), cfg.extraction.budgets(), cfg.extraction.tolerance
            )
            if convergence.steps is not None:
                break

    calibration = resolve(submit(calibrate_task, f"calibration {cfg.name}", inputs, step_config))
    doc = load_calibration_doc(workspace, calibration)
    return {
        "calibration": calibration,
        "extraction": doc["split"]["extraction"],
        "downstream": doc["split"]["downstream"],
        "extraction_steps": doc["extraction"]["steps"],
        "preset_lines": preset_lines(doc),
        "markdown": calibration_markdown(doc),
    }
