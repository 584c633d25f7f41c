"""The `pipeline` flow: the whole CapVector recipe with its baselines, cached step by step.

    demos(D_pt, D_ext, D_down) -> θ_pt -> {θ_ft, θ_ao} on D_ext -> γ = θ_ao − θ_ft -> θ_meta = θ_pt + α·γ
    -> downstream arms × seeds on D_down -> evaluation under one protocol -> comparison report

Independent branches are submitted together and run concurrently on the task runner: a pool of
processes, because steps seed torch's process-global RNG and must not share it, and because two
training steps in two processes use both cores without contending for the GIL. Each worker is bound
to the process that started it (tasks.prefect_task.bind_worker_to_parent): a killed CLI takes its
workers, and their embedded API servers, along.
"""

from __future__ import annotations

from typing import Any

from prefect import flow
from prefect.task_runners import ProcessPoolTaskRunner

from flows.config import ARMS, PipelineConfig
from flows.runs import publish_markdown, recorded_run
from tasks.data import collect_demos_task
from tasks.evaluation import evaluate_task
from tasks.prefect_task import bind_worker_to_parent
from tasks.reporting import report_task
from tasks.training import train_task
from tasks.vectors import extract_task, merge_task
from tasks.workspace import Workspace


def _dump(model: Any) -> dict[str, Any]:
    return model.model_dump(mode="json")


def submit_vector_stage(home: str, config: PipelineConfig) -> dict[str, Any]:
    """Futures for demos, θ_pt, θ_ft, θ_ao, γ and θ_meta."""
    data = {
        split: collect_demos_task.submit(home, f"demos {split}", {}, _dump(config.demo_config(split)))
        for split in ("pretrain", "extraction", "downstream")
    }
    pretrained = train_task.submit(
        home, "pretrain θ_pt", {"data": data["pretrain"]}, _dump(config.pretrain_step())
    )
    extraction_inputs = {"data": data["extraction"], "init": pretrained}
    standard = train_task.submit(
        home, "standard SFT θ_ft", extraction_inputs, _dump(config.extraction_step(False))
    )
    auxiliary = train_task.submit(
        home, "auxiliary SFT θ_ao", extraction_inputs, _dump(config.extraction_step(True))
    )
    vector = extract_task.submit(
        home,
        "capability vector γ",
        {"minuend": auxiliary, "subtrahend": standard, "base": pretrained},
        _dump(config.vector),
    )
    meta = merge_task.submit(
        home,
        f"merge θ_meta (α={config.alpha})",
        {"base": pretrained, "vector": vector},
        _dump(config.merge_config()),
    )
    return {
        "data": data,
        "pretrained": pretrained,
        "standard": standard,
        "auxiliary": auxiliary,
        "vector": vector,
        "meta": meta,
    }


def submit_arm(
    home: str,
    config: PipelineConfig,
    stage: dict[str, Any],
    arm: str,
    seed: int,
    meta: Any = None,
    orthogonal_weight: float | None = None,
    label: str | None = None,
) -> Any:
    """Future of one downstream checkpoint (arm × seed)."""
    spec = ARMS[arm]
    inputs = {
        "data": stage["data"]["downstream"],
        "init": (meta or stage["meta"]) if spec.init == "meta" else stage["pretrained"],
    }
    if spec.orthogonal:
        inputs["vector"] = stage["vector"]
    step_config = config.downstream_step(arm, seed, orthogonal_weight)
    return train_task.submit(home, label or f"downstream {arm} seed {seed}", inputs, _dump(step_config))


def step_runner(workers: int = 2) -> ProcessPoolTaskRunner:
    return ProcessPoolTaskRunner(max_workers=workers, initializer=bind_worker_to_parent)


def _submit_ood_report(home: str, config: PipelineConfig, checkpoints: dict[str, Any]) -> str | None:
    """The same final checkpoints, tested through `evaluation.ood_camera`, in a report of their own."""
    camera = config.evaluation.ood_camera
    if camera is None:
        return None
    eval_config = _dump(config.eval_config(camera=camera))
    evaluations = {
        label: evaluate_task.submit(home, f"evaluate {label} ({camera})", {"checkpoint": ckpt}, eval_config)
        for label, ckpt in checkpoints.items()
    }
    name = f"{config.name} ood camera {camera}"
    return report_task.submit(home, f"report {name}", evaluations, {"name": name}).result()


@flow(name="pipeline", log_prints=True, task_runner=step_runner())
def pipeline(config: dict[str, Any], home: str) -> dict[str, Any]:
    """Run (or resume from cache) the recipe; returns the artifact ids of every product."""
    cfg = PipelineConfig.model_validate(config)
    workspace = Workspace(home)
    with recorded_run(workspace, "pipeline", {"config": config, "home": home}):
        stage = submit_vector_stage(home, cfg)
        eval_config = _dump(cfg.eval_config())
        checkpoints = {
            f"{arm}/seed{seed}": submit_arm(home, cfg, stage, arm, seed)
            for arm in cfg.arms
            for seed in cfg.seeds
        }
        evaluations = {
            label: evaluate_task.submit(home, f"evaluate {label}", {"checkpoint": ckpt}, eval_config)
            for label, ckpt in checkpoints.items()
        }
        # Results in the order the steps depend on each other: a failed step raises its own error here
        # (naming the step), not a later step's UpstreamTaskError naming a task-run id.
        ids = {
            "datasets": {k: f.result() for k, f in stage["data"].items()},
            **{k: stage[k].result() for k in ("pretrained", "standard", "auxiliary", "vector", "meta")},
            "checkpoints": {k: f.result() for k, f in checkpoints.items()},
            "evaluations": {k: f.result() for k, f in evaluations.items()},
        }
        report = report_task.submit(home, f"report {cfg.name}", evaluations, {"name": cfg.name}).result()
        ids["report"] = report
        ood_report = _submit_ood_report(home, cfg, checkpoints)
        if ood_report is not None:
            ids["ood_report"] = ood_report
        table = workspace.api.store.open_json(report)
        publish_markdown(f"{cfg.name}-summary", table["markdown"], f"capvector pipeline {cfg.name}")
    return ids
