"""The `sweep` flow: a grid over α (merge) and λ (the orthogonal loss's weight), chosen on validation seeds.

Validation goal variations (VALIDATION_SEED_BASE) are disjoint from the test seeds the pipeline
reports, so the pick never looks at a test score.
"""

from __future__ import annotations

from typing import Any

from prefect import flow

from capvector.flows.recipe.config import ARMS, PipelineConfig, lambda_label
from capvector.flows.recipe.plan import submit_arm, submit_vector_stage
from capvector.flows.runtime.run_records import publish_markdown, recorded_run, run_name
from capvector.flows.runtime.step_pool import step_runner
from capvector.flows.runtime.step_submission import StepRunner, record_plan, resolve
from capvector.tasks.runtime.workspace import workspace_for
from capvector.tasks.steps.evaluation import evaluate_task
from capvector.tasks.steps.selection import select_task
from capvector.tasks.steps.vectors import merge_task


@flow(name="sweep", flow_run_name=run_name, log_prints=True, task_runner=step_runner(), persist_result=False)
def sweep_flow(config: dict[str, Any], home: str) -> dict[str, Any]:
    cfg = PipelineConfig.model_validate(config)
    workspace = workspace_for(home)
    total = len(record_plan(lambda steps: submit_sweep(steps, cfg)))
    steps = StepRunner(home, total, f"sweep {cfg.name}")
    with recorded_run(workspace, "sweep", {"config": config, "home": home}):
        sweep_id = submit_sweep(steps, cfg)
        doc = workspace.api.store.open_json(sweep_id)
        publish_markdown(f"{cfg.name}-sweep", sweep_markdown(doc), "α × λ sweep on validation seeds")
    return {"sweep": sweep_id, **doc}


def submit_sweep(steps: StepRunner, cfg: PipelineConfig) -> Any:
    """The vector stage, then per α a merge and per λ a run and its validation; the selection's id."""
    arm, seed = cfg.sweep.arm, cfg.seeds[0]
    lambdas = cfg.sweep.lambda_cells(cfg.orthogonal) if ARMS[arm].orthogonal else [{}]
    stage = submit_vector_stage(steps, cfg)
    validation = cfg.eval_config(validation=True).model_dump(mode="json")
    cells = []
    for alpha in cfg.sweep.alphas:
        meta = steps.submit(
            merge_task,
            f"merge θ_meta (α={alpha})",
            {"base": stage["pretrained"], "vector": stage["vector"]},
            cfg.merge_config(alpha).model_dump(mode="json"),
        )
        for lam in lambdas:
            label = f"{arm} α={alpha} {lambda_label(lam)}"
            checkpoint = submit_arm(
                steps, stage, arm, seed, cfg.downstream_step(arm, seed, lam or None), label=label, meta=meta
            )
            evaluation = steps.submit(
                evaluate_task, f"validate {label}", {"checkpoint": checkpoint}, validation
            )
            cells.append({"values": {"alpha": alpha, **lam}, "evaluation": evaluation})
    selection = {
        "name": "α and λ",
        "context": {"arm": arm, "seed": seed},
        "candidates": [{"values": c["values"], "evaluations": [f"cell {i}"]} for i, c in enumerate(cells)],
    }
    evaluations = {f"cell {i}": c["evaluation"] for i, c in enumerate(cells)}
    return resolve(steps.submit(select_task, f"sweep {cfg.name}", evaluations, selection))


def sweep_markdown(doc: dict[str, Any]) -> str:
    lines = ["| α | λ | validation success |", "|---|---|---|"]
    for r in doc["grid"]:
        mark = " **(best)**" if r == doc["best"] else ""
        lines.append(f"| {r['alpha']} | {lambda_label(r)} | {100 * r['validation_success']:.1f}%{mark} |")
    return "\n".join(lines) + "\n"
