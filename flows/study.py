"""The `study` flow: a whole experiment on CapVector, from demonstrations to the analysed report.

    demos -> θ_pt
    -> extraction lr chosen on D_ext validation goals          (selection artifact)
    -> auxiliary weight chosen (downstream, validation goals)  (selection artifact; θ_ao uses it too)
    -> a tuning γ (tuning seed) -> α × λ chosen for CapVector on it (validation goals) (selection artifact)
    -> per γ draw d: θ_ft^d, θ_ao^d (chosen lr) -> γ^d, γ_null^d (random, γ^d's per-tensor norms)
    -> per draw: θ_meta^d = θ_pt + α·γ^d, θ_null^d = θ_pt + α·γ_null^d
    -> arms × draws × seeds, each kept at every curve budget, evaluated on the same test goals
    -> preconditions, paired comparisons with hierarchical-bootstrap CIs, MDD -> `study` artifact

Every value is chosen on validation goals by a `select` step whose parents are the evaluations it
chose from, and every run that uses the value has the selection as an input (lineage: `selected_by`).
Selection runs use `study.tuning_seed`, never a compared run's seed. The flow blocks only where a
choice is needed to configure the next runs; everything else is submitted at once (flows.steps).
"""

from __future__ import annotations

from typing import Any

from prefect import flow

from flows.pipeline import step_runner, submit_arm
from flows.runs import publish_markdown, recorded_run
from flows.steps import StepRunner, resolve
from flows.study_config import SHARED_ARMS, StudyConfig
from tasks.data import collect_demos_task
from tasks.evaluation import evaluate_task
from tasks.held_out_loss import held_out_loss_task
from tasks.selection import chosen, select_task
from tasks.study_analysis import analyse_study_task, label
from tasks.study_report import load_study_report, study_markdown
from tasks.training import snapshots_of, train_task
from tasks.vectors import extract_task, merge_task, null_vector_task
from tasks.workspace import Workspace, workspace_for


def _dump(model: Any) -> dict[str, Any]:
    return model.model_dump(mode="json")


def study_steps(cfg: StudyConfig) -> int:
    """How many steps a study submits (progress shows `k/N`)."""
    s = cfg.study
    cells = len(s.alphas) * len(s.lambda_scales)
    runs = sum(len(cfg.seeds) * (1 if arm in SHARED_ARMS else len(s.draws)) for arm in s.arms)
    lr_grid = 3 * len(s.extraction_lrs) + 1  # runs, validations, held-out losses, selection
    aux_grid = 2 * cells + 1 if "aux" in s.arms else 0  # runs, validations, selection
    tuning_vector = 2  # θ_ao at the tuning seed, its γ
    lambda_grid = len(s.alphas) + 2 * cells + 1  # merges, runs, validations, selection
    per_draw = 15  # θ_ft, θ_ao, γ, γ_null, 2 validations, 6 held-out losses, 2 merges, θ_meta's validation
    compared = runs * (1 + len(cfg.curve_budgets))  # the runs and their test evaluations
    demos_and_pretraining, pt_validation, analysis = 5, 1, 1
    return (
        demos_and_pretraining
        + lr_grid
        + aux_grid
        + tuning_vector
        + lambda_grid
        + per_draw * len(s.draws)
        + pt_validation
        + compared
        + analysis
    )


class _Study:
    """The flow's state: its config, where steps go, and what was submitted so far."""

    def __init__(self, cfg: StudyConfig, steps: StepRunner, workspace: Workspace):
        self.cfg, self.steps, self.workspace = cfg, steps, workspace
        self.analysis_inputs: dict[str, Any] = {}

    def submit(self, task: Any, step: str, inputs: dict[str, Any], config: Any) -> Any:
        return self.steps.submit(task, step, inputs, config if isinstance(config, dict) else _dump(config))

    def at_budget(self, checkpoint: Any, budget: int) -> str:
        """The id of the checkpoint a run kept after `budget` steps (waits for the run)."""
        return snapshots_of(self.workspace, resolve(checkpoint))[budget]

    def select(
        self,
        name: str,
        cells: list[tuple[dict[str, Any], Any]],
        context: dict[str, Any],
        tiebreaks: list[Any] = (),
    ) -> str:
        """A `select` step over (values, validation evaluation) cells, ties broken by the `tiebreaks`
        (held-out loss measurements, one per cell) when given; its id (waits for it)."""
        inputs = {f"cell {i}": evaluation for i, (_, evaluation) in enumerate(cells)}
        inputs |= {f"loss {i}": m for i, m in enumerate(tiebreaks)}
        candidates = [{"values": v, "evaluation": f"cell {i}"} for i, (v, _) in enumerate(cells)]
        for i, c in enumerate(candidates[: len(tiebreaks)]):
            c["tiebreak"] = f"loss {i}"
        config = {"name": name, "context": context, "candidates": candidates}
        selection = resolve(self.submit(select_task, f"select {name}", inputs, config))
        self.analysis_inputs[label("selection", name)] = selection
        return selection


def _run_study(study: _Study) -> dict[str, Any]:
    cfg, s, submit = study.cfg, study.cfg.study, study.submit
    tune = s.tuning_seed
    validation_down = cfg.eval_config(validation=True)
    validation_ext = cfg.extraction_validation()

    data = {
        split: submit(collect_demos_task, f"demos {split}", {}, cfg.demo_config(split))
        for split in ("pretrain", "extraction", "downstream")
    }
    data["heldout"] = submit(collect_demos_task, "demos extraction (held out)", {}, cfg.heldout_demo_config())
    pretrained = submit(train_task, "pretrain θ_pt", {"data": data["pretrain"]}, cfg.pretrain_step())
    base_stage = {"data": data, "pretrained": pretrained}

    # Everything that needs no choice yet: the lr grid, the auxiliary grid, SFT's runs.
    extraction_inputs = {"data": data["extraction"], "init": pretrained}
    lr_runs, lr_cells, lr_losses = {}, [], []
    for lr in s.extraction_lrs:
        step = f"tune extraction θ_ft lr={lr}"
        lr_runs[lr] = submit(train_task, step, extraction_inputs, cfg.extraction_run(False, tune, lr))
        validation = submit(
            evaluate_task, f"validate θ_ft lr={lr}", {"checkpoint": lr_runs[lr]}, validation_ext
        )
        lr_cells.append(({"lr": lr}, validation))
        held_out = {"checkpoint": lr_runs[lr], "data": data["heldout"]}
        lr_losses.append(submit(held_out_loss_task, f"held-out loss θ_ft lr={lr}", held_out, {}))
    tuned_aux = "aux" in s.arms
    aux_runs = [
        (
            w,
            submit_arm(
                study.steps,
                cfg,
                base_stage,
                "aux",
                tune,
                label=f"tune aux weight={w}",
                step_config=cfg.study_downstream("aux", tune, aux_weight=w),
            ),
        )
        for w in (s.aux_weights if tuned_aux else [])
    ]
    runs: dict[tuple[str, int, int], Any] = {}  # (arm, draw, seed) -> checkpoint
    shared = -1
    for seed in cfg.seeds:
        runs["sft", shared, seed] = submit_arm(
            study.steps, cfg, base_stage, "sft", seed, step_config=cfg.study_downstream("sft", seed)
        )
    pt_validation = submit(
        evaluate_task, "validate θ_pt on D_ext", {"checkpoint": pretrained}, validation_ext
    )
    study.analysis_inputs[label("extval", "pt", shared)] = pt_validation

    # Choices on validation goals at the selection budget.
    budget = cfg.select_budget

    def validate(values: dict[str, Any], run: Any, what: str) -> tuple[dict[str, Any], Any]:
        step = f"validate {what} @ {budget}"
        return values, submit(
            evaluate_task, step, {"checkpoint": study.at_budget(run, budget)}, validation_down
        )

    # (a) the extraction lr; the auxiliary weight (θ_ao is trained with the weight the aux arm uses).
    lr_selection = study.select("extraction lr", lr_cells, {"run": "θ_ft", "seed": tune}, lr_losses)
    lr = chosen(study.workspace, lr_selection)["lr"]
    extraction_choices = {"selection": lr_selection}
    aux_weight = cfg.aux.weight
    if tuned_aux:
        aux_cells = [validate({"aux_weight": w}, run, f"aux weight={w}") for w, run in aux_runs]
        aux_selection = study.select("auxiliary weight", aux_cells, {"seed": tune, "budget": budget})
        aux_weight = chosen(study.workspace, aux_selection)["aux_weight"]
        extraction_choices["selection aux"] = aux_selection
        for seed in cfg.seeds:
            runs["aux", shared, seed] = submit_arm(
                study.steps,
                cfg,
                base_stage,
                "aux",
                seed,
                selection=aux_selection,
                step_config=cfg.study_downstream("aux", seed, aux_weight=aux_weight),
            )

    # The tuning γ (tuning seed, never a compared draw) and the α × λ grid on it.
    inputs = {**extraction_inputs, **extraction_choices}  # θ_ao's: the lr and the auxiliary weight
    standard_inputs = {**extraction_inputs, "selection": lr_selection}  # θ_ft uses the lr only
    tuning_ao = submit(
        train_task, "tune extraction θ_ao", inputs, cfg.extraction_run(True, tune, lr, aux_weight)
    )
    tuning_stage = {
        **base_stage,
        "vector": submit(
            extract_task,
            "tuning capability vector γ",
            {"minuend": tuning_ao, "subtrahend": lr_runs[lr], "base": pretrained},
            cfg.vector,
        ),
    }
    grid_runs = []
    for alpha in s.alphas:
        meta = submit(
            merge_task,
            f"tune merge θ_meta α={alpha}",
            {"base": pretrained, "vector": tuning_stage["vector"]},
            cfg.merge_config(alpha),
        )
        for scale in s.lambda_scales:
            run = submit_arm(
                study.steps,
                cfg,
                tuning_stage,
                "capvector",
                tune,
                meta=meta,
                label=f"tune capvector α={alpha} λ={scale}",
                step_config=cfg.study_downstream("capvector", tune, lambda_scale=scale),
            )
            grid_runs.append(({"alpha": alpha, "lambda_scale": scale}, run))

    # Every draw's θ_ft, θ_ao, γ and null vector (while the grid trains).
    draws: dict[int, dict[str, Any]] = {}
    for d in s.draws:
        ft = submit(
            train_task, f"draw {d} standard SFT θ_ft", standard_inputs, cfg.extraction_run(False, d, lr)
        )
        ao = submit(
            train_task, f"draw {d} auxiliary SFT θ_ao", inputs, cfg.extraction_run(True, d, lr, aux_weight)
        )
        vector = submit(
            extract_task,
            f"draw {d} capability vector γ",
            {"minuend": ao, "subtrahend": ft, "base": pretrained},
            cfg.vector,
        )
        null = submit(null_vector_task, f"draw {d} null vector", {"vector": vector}, {"seed": d})
        for which, run in (("ft", ft), ("ao", ao)):
            study.analysis_inputs[label("extval", which, d)] = submit(
                evaluate_task, f"validate draw {d} θ_{which} on D_ext", {"checkpoint": run}, validation_ext
            )
        draws[d] = {**base_stage, "standard": ft, "auxiliary": ao, "vector": vector, "null_vector": null}
        for arm in ("sft_from_ao", "sft_from_ft"):
            if arm in s.arms:
                for seed in cfg.seeds:
                    runs[arm, d, seed] = submit_arm(
                        study.steps, cfg, draws[d], arm, seed, step_config=cfg.study_downstream(arm, seed)
                    )

    grid_cells = [validate(v, run, f"capvector α={v['alpha']} λ={v['lambda_scale']}") for v, run in grid_runs]
    grid_selection = study.select("α and λ", grid_cells, {"seed": tune, "budget": budget})
    best = chosen(study.workspace, grid_selection)
    alpha, scale = best["alpha"], best["lambda_scale"]

    merge = cfg.merge_config(alpha)
    for d, stage in draws.items():
        stage["meta"] = submit(
            merge_task,
            f"draw {d} merge θ_meta",
            {"base": pretrained, "vector": stage["vector"], "selection": grid_selection},
            merge,
        )
        stage["null_meta"] = submit(
            merge_task,
            f"draw {d} merge θ_null",
            {"base": pretrained, "vector": stage["null_vector"], "selection": grid_selection},
            merge,
        )
        study.analysis_inputs[label("extval", "meta", d)] = submit(
            evaluate_task, f"validate draw {d} θ_meta on D_ext", {"checkpoint": stage["meta"]}, validation_ext
        )
        for arm in ("meta_sft", "capvector", "null_capvector"):
            if arm in s.arms:
                for seed in cfg.seeds:
                    runs[arm, d, seed] = submit_arm(
                        study.steps,
                        cfg,
                        stage,
                        arm,
                        seed,
                        selection=grid_selection,
                        step_config=cfg.study_downstream(
                            arm, seed, lambda_scale=scale if arm != "meta_sft" else None
                        ),
                    )

    # Test goals: every compared run at every budget; the extraction runs' held-out losses.
    test = cfg.eval_config()
    for (arm, d, seed), run in runs.items():
        for b, checkpoint in snapshots_of(study.workspace, resolve(run)).items():
            step = f"test {arm}" + ("" if d == shared else f" draw {d}") + f" seed {seed} @ {b}"
            study.analysis_inputs[label("test", arm, d, seed, b)] = submit(
                evaluate_task, step, {"checkpoint": checkpoint}, test
            )
    for d, stage in draws.items():
        for which in ("standard", "auxiliary"):
            kept = snapshots_of(study.workspace, resolve(stage[which]))
            for b in kept:  # half, three quarters, the end
                study.analysis_inputs[label("loss", which, d, b)] = submit(
                    held_out_loss_task,
                    f"held-out loss draw {d} {which} @ {b}",
                    {"checkpoint": kept[b], "data": data["heldout"]},
                    {},
                )

    inputs = {k: resolve(v) for k, v in study.analysis_inputs.items()}
    design = {
        "name": cfg.name,
        "arms": list(s.arms),
        "draws": list(s.draws),
        "seeds": list(cfg.seeds),
        "primary_budget": s.primary_budget,
        "final_budget": cfg.downstream.steps,
        "extraction_steps": cfg.extraction.steps,
        "flat_tolerance": s.flat_tolerance,
        "non_inferiority_margin": s.non_inferiority_margin,
        "n_boot": s.n_boot,
        "chosen": {"extraction_lr": lr, "aux_weight": aux_weight, "alpha": alpha, "lambda_scale": scale},
        "grids": {
            "extraction_lr": list(s.extraction_lrs),
            "aux_weight": list(s.aux_weights) if tuned_aux else [aux_weight],
            "alpha": list(s.alphas),
            "lambda_scale": list(s.lambda_scales),
        },
    }
    report = resolve(submit(analyse_study_task, f"analyse study {cfg.name}", inputs, design))
    return {"report": report, "selections": {k: v for k, v in inputs.items() if k.startswith("selection")}}


@flow(name="study", log_prints=True, task_runner=step_runner(), persist_result=False)
def study_flow(config: dict[str, Any], home: str) -> dict[str, Any]:
    """Run (or resume from cache) a study; returns the report's id and the selections' ids."""
    cfg = StudyConfig.model_validate(config)
    workspace = workspace_for(home)
    steps = StepRunner(home, study_steps(cfg), f"study {cfg.name}")
    with recorded_run(workspace, "study", {"config": config, "home": home}):
        ids = _run_study(_Study(cfg, steps, workspace))
        markdown = study_markdown(workspace, load_study_report(workspace, ids["report"]))
        publish_markdown(f"{cfg.name}-study", markdown, f"capvector study {cfg.name}")
    return {**ids, "markdown": markdown}
