"""A study's plan: a whole experiment on CapVector, from demonstrations to the analysed report (the
`study` flow, capvector.flows.study.flow, runs it; without Prefect here, a study the cache answers never loads
it).

    demos -> θ_pt
    -> extraction lr chosen for θ_ft on D_ext validation goals               (selection artifact)
    -> θ_ao's auxiliary weight chosen on D_ext validation goals               (selection artifact)
    -> the downstream auxiliary arm's weight chosen on D_down validation goals (selection artifact)
    -> per γ draw d: θ_ft^d, θ_ao^d -> γ^d, γ_null^d (random, γ^d's per-tensor norms)
    -> the gate: SFT, auxiliary SFT, SFT from θ_ao^d and from θ_ft^d, tested; CapVector's arms run only
       when precondition (b) (θ_ao beats θ_ft on D_ext) and (c) (SFT from θ_ao beats SFT from θ_ft on
       D_down) hold with intervals above 0 — otherwise the report says why the question is untestable
    -> the tuning γ (tuning seed's θ_ao − θ_ft) -> α × λ chosen for CapVector (validation goals)
    -> per draw: θ_meta^d = θ_pt + α·γ^d, θ_null^d = θ_pt + α·γ_null^d -> the remaining arms × seeds
    -> every run kept at every budget (and its start, budget 0) and tested on the same test goals
    -> preconditions (a)-(e) and (c′), paired comparisons with t intervals (df shown), MDD -> `study` artifact

The primary endpoint is the mean success over the declared budgets (the area under the
success-vs-steps curve), and every value is chosen on validation goals at that same endpoint by a
`select` step whose parents are the evaluations it chose from; every run that uses the value has the
selection as an input (lineage: `selected_by`). Selection runs use `study.tuning_seed`, never a
compared run's seed. The flow blocks only where a choice (or the gate) configures the next runs;
everything else is submitted at once (capvector.flows.runtime.step_submission).
"""

from __future__ import annotations

from typing import Any

from capvector.flows.recipe.config import ARMS
from capvector.flows.recipe.plan import submit_arm
from capvector.flows.runtime.step_submission import CacheProbe, PlannedStep, PlanRecorder, StepRunner, resolve
from capvector.flows.study.config import GATE_ARMS, SHARED_ARMS, StudyConfig
from capvector.flows.study.report import load_study_report, study_markdown
from capvector.tasks.runtime.progress import emit
from capvector.tasks.runtime.workspace import Workspace, workspace_for
from capvector.tasks.steps.data import collect_demos_task
from capvector.tasks.steps.evaluation import evaluate_task
from capvector.tasks.steps.held_out_loss import held_out_loss_task
from capvector.tasks.steps.selection import chosen, select_task
from capvector.tasks.steps.study_analysis import analyse_study_task, gate_passed
from capvector.tasks.steps.training import snapshots_of, train_task
from capvector.tasks.steps.vectors import extract_task, mean_vector_task, merge_task, null_vector_task
from capvector.tasks.study_inputs import (
    CapabilityVector,
    DownstreamLoss,
    ExtractionValidation,
    HeldOutLoss,
    InputKey,
    Pretrained,
    ReplicateVector,
    Selection,
    StandardRun,
    TestEvaluation,
)

SHARED = -1
"""The draw of an arm shared by every γ draw (capvector.stats.paired_differences.SHARED_DRAW)."""


def _dump(model: Any) -> dict[str, Any]:
    return model.model_dump(mode="json")


def study_plan(cfg: StudyConfig) -> list[PlannedStep]:
    """Every step the study submits when its gate passes, in order, from the flow's own code run
    against a recorder: nothing runs or is looked up, and each choice takes its first candidate
    (a choice changes a step's config, never how many steps follow)."""
    return gated_study_plan(cfg)[0]


def gated_study_plan(cfg: StudyConfig) -> tuple[list[PlannedStep], int]:
    """The study's plan and where its gate falls: the number of steps submitted up to and including
    the gate's analysis (every step when `study.gate` is off). The steps after it run only if the
    gate passes."""
    recorder = PlanRecorder()
    study = _PlannedStudy(cfg, recorder)
    _run_study(study)
    return recorder.plan, study.gate_at if study.gate_at is not None else len(recorder.plan)


def study_steps(cfg: StudyConfig) -> tuple[int, int]:
    """How many steps a study submits before its gate (all of them when it has none), and how many
    more after it if the gate passes: progress counts `k/N` to the first, then adds the second once
    the gate has passed."""
    plan, gate_at = gated_study_plan(cfg)
    return gate_at, len(plan) - gate_at


def after_gate(steps: Any, more: int) -> None:
    """The gate passed: the runner's announced total grows by the steps that now follow it."""
    if more and hasattr(steps, "total"):
        steps.total += more
        if not isinstance(steps, CacheProbe):  # a probe only looks: it says nothing until it replays
            emit(f"[{steps.label}] gate passed: {more} more steps, {steps.total} in all")


def _start_kind(arm: str) -> str:
    """Which checkpoint an arm's run starts from (runs starting alike share their budget-0 test)."""
    return ARMS[arm].init


class _Study:
    """The flow's state: its config, where steps go, and what was submitted so far."""

    def __init__(self, cfg: StudyConfig, steps: StepRunner, workspace: Workspace):
        self.cfg, self.steps, self.workspace = cfg, steps, workspace
        self.analysis_inputs: dict[str, Any] = {}
        self.test = cfg.eval_config()
        self.validation_down = cfg.eval_config(validation=True)
        self.validation_ext = cfg.extraction_validation()
        self._started: dict[tuple[str, int], Any] = {}
        self.heldout_downstream: Any = None  # held-out D_down demos (the secondary endpoint)
        self.unit = "replicate" if cfg.study.draws_per_replicate > 1 else "draw"
        """What CapVector's arms are compared over: γ draws, or replicates (means of K draws)."""
        self.gate_more = 0
        """The steps that follow a passed gate (the runner's total grows by them then)."""

    def submit(self, task: Any, step: str, inputs: dict[str, Any], config: Any) -> Any:
        return self.steps.submit(task, step, inputs, config if isinstance(config, dict) else _dump(config))

    def record(self, key: InputKey, value: Any) -> None:
        """An input of the study's analysis, under its typed key (capvector.tasks.study_inputs)."""
        self.analysis_inputs[key.key] = value

    def snapshots(self, run: Any) -> dict[int, str]:
        """Budget -> the checkpoint a run kept after that many steps (waits for the run)."""
        return snapshots_of(self.workspace, resolve(run))

    def chosen(self, selection: str) -> dict[str, Any]:
        """The values a selection chose."""
        return chosen(self.workspace, selection)

    def gate_passed(self, report: str) -> bool:
        return gate_passed(self.workspace, report)

    def at_budget(self, checkpoint: Any, budget: int) -> Any:
        """The checkpoint a run kept after `budget` steps (waits for the run)."""
        return self.snapshots(checkpoint)[budget]

    def train_draw_arm(
        self, stage: dict[str, Any], arm: str, d: int, seed: int, step: Any, selection: Any = None
    ) -> Any:
        """A compared run of an arm that depends on draw (or replicate) d (its name carries it: unique)."""
        label = f"downstream {arm} {self.unit} {d} seed {seed}"
        return submit_arm(self.steps, stage, arm, seed, step, label=label, selection=selection)

    def validate_curve(self, run: Any, what: str) -> list[Any]:
        """A downstream run's validation evaluations at every curve budget (its endpoint's parts)."""
        return [
            self.submit(
                evaluate_task,
                f"validate {what} @ {b}",
                {"checkpoint": self.at_budget(run, b)},
                self.validation_down,
            )
            for b in self.cfg.curve_budgets
        ]

    def select(
        self,
        name: str,
        cells: list[tuple[dict[str, Any], list[Any]]],
        context: dict[str, Any],
        tiebreaks: list[Any] = (),
    ) -> str:
        """A `select` step over (values, validation evaluations) cells — a cell's score is the mean over
        its evaluations — ties broken by the `tiebreaks` (held-out loss measurements, one per cell)
        when given; its id (waits for it)."""
        inputs = {f"cell {i} @ {j}": e for i, (_, evals) in enumerate(cells) for j, e in enumerate(evals)}
        inputs |= {f"loss {i}": m for i, m in enumerate(tiebreaks)}
        candidates = [
            {"values": v, "evaluations": [f"cell {i} @ {j}" for j in range(len(evals))]}
            for i, (v, evals) in enumerate(cells)
        ]
        for i, c in enumerate(candidates[: len(tiebreaks)]):
            c["tiebreak"] = f"loss {i}"
        config = {"name": name, "context": context, "candidates": candidates}
        selection = resolve(self.submit(select_task, f"select {name}", inputs, config))
        self.record(Selection(name=name), selection)
        return selection

    def test_start(self, checkpoint: Any, arm: str, draw: int, what: str) -> None:
        """Budget 0: the checkpoint a run starts from, tested once and counted for every seed."""
        key = (_start_kind(arm), draw)
        if key not in self._started:
            self._started[key] = self.submit(
                evaluate_task, f"test {what} @ 0", {"checkpoint": checkpoint}, self.test
            )
        for seed in self.cfg.seeds:
            self.record(TestEvaluation(arm=arm, draw=draw, seed=seed, budget=0), self._started[key])

    def test_runs(self, runs: dict[tuple[str, int, int], Any]) -> None:
        """Every compared run at every budget, on the same test goals; its final checkpoint's held-out
        action loss on D_down (the continuous secondary endpoint)."""
        for (arm, d, seed), run in runs.items():
            what = f"{arm}" + ("" if d == SHARED else f" {self.unit} {d}") + f" seed {seed}"
            for b, checkpoint in self.snapshots(run).items():
                test = self.submit(evaluate_task, f"test {what} @ {b}", {"checkpoint": checkpoint}, self.test)
                self.record(TestEvaluation(arm=arm, draw=d, seed=seed, budget=b), test)
            held_out = {"checkpoint": run, "data": self.heldout_downstream}
            loss = self.submit(held_out_loss_task, f"held-out loss D_down {what}", held_out, {})
            self.record(DownstreamLoss(arm=arm, draw=d, seed=seed), loss)

    def analyse(self, stage: str, design: dict[str, Any]) -> str:
        inputs = {k: resolve(v) for k, v in self.analysis_inputs.items()}
        name = f"analyse study {self.cfg.name}" + (" (gate)" if stage == "gate" else "")
        return resolve(self.submit(analyse_study_task, name, inputs, {**design, "stage": stage}))


class _PlannedStudy(_Study):
    """The study as a plan: its reads are answered from the recorded steps' configs, not the store."""

    def __init__(self, cfg: StudyConfig, recorder: PlanRecorder):
        super().__init__(cfg, recorder, None)
        self.gate_at: int | None = None
        """How many steps were submitted when the gate was asked (its analysis included)."""

    def snapshots(self, run: PlannedStep) -> dict[int, PlannedStep]:
        train = run.config["train"]
        return {b: run for b in sorted({*train["snapshot_steps"], train["steps"]})}

    def chosen(self, selection: PlannedStep) -> dict[str, Any]:
        return selection.config["candidates"][0]["values"]

    def gate_passed(self, report: PlannedStep) -> bool:
        self.gate_at = len(self.steps.plan)
        return True


def _seeded(label: str, seed: int, tunes: list[int]) -> str:
    """A tuning step's label, naming its seed where there are several."""
    return f"{label} seed {seed}" if len(tunes) > 1 else label


def _extraction(study: _Study, data: dict[str, Any], pretrained: Any) -> dict[str, Any]:
    """The extraction lr for θ_ft and θ_ao's auxiliary weight, each chosen on D_ext validation goals
    from runs at every tuning seed (a cell's score: its mean over them; ties: the first tuning seed's
    lower held-out action loss); returns the choices and each tuning seed's θ_ft and θ_ao (the tuning
    γs' ends)."""
    cfg, s, submit, tunes = study.cfg, study.cfg.study, study.submit, study.cfg.study.tuning_seeds
    inputs = {"data": data["extraction"], "init": pretrained}

    def grid(what: str, configs: dict[Any, dict[int, Any]], extra: dict[str, Any]) -> tuple[dict, list, list]:
        runs, cells, losses = {}, [], []
        for value, by_seed in configs.items():
            evaluations = []
            for t, config in by_seed.items():
                label = _seeded(f"{what}={value}", t, tunes)
                runs[value, t] = submit(train_task, f"tune extraction {label}", {**inputs, **extra}, config)
                checkpoint = {"checkpoint": runs[value, t]}
                validation = submit(evaluate_task, f"validate {label}", checkpoint, study.validation_ext)
                evaluations.append(validation)
                if t == tunes[0]:
                    held_out = {**checkpoint, "data": data["heldout"]}
                    losses.append(submit(held_out_loss_task, f"held-out loss {label}", held_out, {}))
            cells.append((value, evaluations))
        return runs, cells, losses

    ft_configs = {lr: {t: cfg.extraction_run(False, t, lr) for t in tunes} for lr in s.extraction_lrs}
    ft_runs, cells, losses = grid("θ_ft lr", ft_configs, {})
    lr_selection = study.select(
        "extraction lr", [({"lr": v}, e) for v, e in cells], {"run": "θ_ft", "seeds": tunes}, losses
    )
    lr = study.chosen(lr_selection)["lr"]
    ao_configs = {
        w: {t: cfg.extraction_run(True, t, lr, w) for t in tunes} for w in s.extraction_aux_weights
    }
    ao_runs, cells, losses = grid("θ_ao aux weight", ao_configs, {"selection": lr_selection})
    weight_selection = study.select(
        "extraction auxiliary weight",
        [({"aux_weight": v}, e) for v, e in cells],
        {"run": "θ_ao", "seeds": tunes},
        losses,
    )
    weight = study.chosen(weight_selection)["aux_weight"]
    return {
        "lr": lr,
        "aux_weight": weight,
        "lr_selection": lr_selection,
        "weight_selection": weight_selection,
        "standard": {t: ft_runs[lr, t] for t in tunes},
        "auxiliary": {t: ao_runs[weight, t] for t in tunes},
    }


def _draw(
    study: _Study, d: int, stage: dict[str, Any], extraction: dict[str, Any], compared: bool = True
) -> dict[str, Any]:
    """θ_ft^d and θ_ao^d with the chosen values, γ^d, and (for a compared draw) their D_ext validations."""
    cfg, submit = study.cfg, study.submit
    inputs = {
        "data": stage["data"]["extraction"],
        "init": stage["pretrained"],
        "selection": extraction["lr_selection"],
    }
    lr, weight = extraction["lr"], extraction["aux_weight"]
    ft = submit(train_task, f"draw {d} standard SFT θ_ft", inputs, cfg.extraction_run(False, d, lr))
    ao_inputs = {**inputs, "selection aux": extraction["weight_selection"]}
    ao = submit(
        train_task, f"draw {d} auxiliary SFT θ_ao", ao_inputs, cfg.extraction_run(True, d, lr, weight)
    )
    vector = submit(
        extract_task,
        f"draw {d} capability vector γ",
        {"minuend": ao, "subtrahend": ft, "base": stage["pretrained"]},
        cfg.vector,
    )
    if compared:
        for which, run in (("ft", ft), ("ao", ao)):
            validation = submit(
                evaluate_task,
                f"validate draw {d} θ_{which} on D_ext",
                {"checkpoint": run},
                study.validation_ext,
            )
            study.record(ExtractionValidation(which=which, draw=d), validation)
        study.record(CapabilityVector(draw=d), vector)
        study.record(StandardRun(draw=d), ft)
    return {**stage, "standard": ft, "auxiliary": ao, "vector": vector}


def _units(study: _Study, draws: dict[int, dict[str, Any]]) -> dict[int, dict[str, Any]]:
    """The units CapVector's arms are compared over, each with its vector and null vector: the draws, or
    with `study.draws_per_replicate` K > 1 the replicates, each the mean γ̄^r of K consecutive draws
    (its θ_ft and θ_ao, which SFT from θ_ao / θ_ft start from, are its first draw's)."""
    k = study.cfg.study.draws_per_replicate
    units = dict(draws)
    if k > 1:
        ids = sorted(draws)
        units = {}
        for r in range(len(ids) // k):
            group = ids[r * k : (r + 1) * k]
            inputs = {f"vector {i}": draws[d]["vector"] for i, d in enumerate(group)}
            vector = study.submit(mean_vector_task, f"replicate {r} mean capability vector γ̄", inputs, {})
            study.record(ReplicateVector(replicate=r), vector)
            units[r] = {**draws[group[0]], "vector": vector}
    for u, unit in units.items():
        null_inputs = {"vector": unit["vector"]}
        label = f"{study.unit} {u} null vector"
        unit["null_vector"] = study.submit(null_vector_task, label, null_inputs, {"seed": u})
    return units


def _held_out_losses(study: _Study, draws: dict[int, dict[str, Any]], heldout: Any) -> None:
    """Each extraction run's held-out action loss at half, three quarters and the end (precondition a)."""
    for d, stage in draws.items():
        for which in ("standard", "auxiliary"):
            kept = study.snapshots(stage[which])
            for b in kept:
                loss = study.submit(
                    held_out_loss_task,
                    f"held-out loss draw {d} {which} @ {b}",
                    {"checkpoint": kept[b], "data": heldout},
                    {},
                )
                study.record(HeldOutLoss(which=which, draw=d, budget=b), loss)


def _foundations(study: _Study) -> dict[str, Any]:
    """Demonstrations and θ_pt: what every run starts from (`data`, `pretrained`)."""
    cfg, submit = study.cfg, study.submit
    data = {
        split: submit(collect_demos_task, f"demos {split}", {}, cfg.demo_config(split))
        for split in ("pretrain", "extraction", "downstream")
    }
    data["heldout"] = submit(collect_demos_task, "demos extraction (held out)", {}, cfg.heldout_demo_config())
    study.heldout_downstream = submit(
        collect_demos_task, "demos downstream (held out)", {}, cfg.downstream_heldout_demo_config()
    )
    pretrained = submit(train_task, "pretrain θ_pt", {"data": data["pretrain"]}, cfg.pretrain_step())
    pt_validation = submit(
        evaluate_task, "validate θ_pt on D_ext", {"checkpoint": pretrained}, study.validation_ext
    )
    study.record(ExtractionValidation(which="pt", draw=SHARED), pt_validation)
    study.record(Pretrained(), pretrained)
    return {"data": data, "pretrained": pretrained}


def _aux_grid(study: _Study, base: dict[str, Any]) -> list[tuple[float, list[Any]]]:
    """The downstream auxiliary arm's weight grid, one run per tuning seed and weight."""
    cfg, s, tunes = study.cfg, study.cfg.study, study.cfg.study.tuning_seeds
    if "aux" not in s.arms:
        return []
    return [
        (
            w,
            [
                submit_arm(
                    study.steps,
                    base,
                    "aux",
                    t,
                    cfg.study_downstream("aux", t, aux_weight=w),
                    label=_seeded(f"tune aux weight={w}", t, tunes),
                )
                for t in tunes
            ],
        )
        for w in s.aux_weights
    ]


def _aux_runs(study: _Study, base: dict[str, Any], aux_grid: list, runs: dict, chosen_values: dict) -> None:
    """The downstream auxiliary weight, chosen on the endpoint the study is judged at; its compared runs."""
    cfg, tunes = study.cfg, study.cfg.study.tuning_seeds
    cells = [
        (
            {"aux_weight": w},
            [
                e
                for t, run in zip(tunes, tuning_runs, strict=True)
                for e in study.validate_curve(run, _seeded(f"aux weight={w}", t, tunes))
            ],
        )
        for w, tuning_runs in aux_grid
    ]
    aux_selection = study.select("auxiliary weight", cells, {"seeds": tunes, "endpoint": cfg.curve_budgets})
    chosen_values["aux_weight"] = study.chosen(aux_selection)["aux_weight"]
    for seed in cfg.seeds:
        step = cfg.study_downstream("aux", seed, aux_weight=chosen_values["aux_weight"])
        runs["aux", SHARED, seed] = submit_arm(study.steps, base, "aux", seed, step, selection=aux_selection)


def _gate_arms(study: _Study, units: dict[int, dict[str, Any]], runs: dict) -> None:
    """SFT from each unit's θ_ao and θ_ft: preconditions (c) and (c′) with SFT."""
    for d, stage in units.items():
        for arm in [a for a in ("sft_from_ao", "sft_from_ft") if a in study.cfg.study.arms]:
            start = stage["auxiliary" if arm == "sft_from_ao" else "standard"]
            study.test_start(start, arm, d, f"{study.unit} {d} {arm} start")
            for seed in study.cfg.seeds:
                step = study.cfg.study_downstream(arm, seed)
                runs[arm, d, seed] = study.train_draw_arm(stage, arm, d, seed, step)


def _tuning_vectors(study: _Study, base: dict[str, Any], extraction: dict[str, Any]) -> dict[int, Any]:
    """Tuning seed -> the γ its α × λ runs use: the mean γ̄_tune of `study.tuning_vector_draws` (one for
    every tuning seed), else each tuning seed's own θ_ao − θ_ft from the extraction grid."""
    cfg, s, submit, tunes = study.cfg, study.cfg.study, study.submit, study.cfg.study.tuning_seeds
    if s.tuning_vector_draws:
        draws = {d: _draw(study, d, base, extraction, compared=False) for d in s.tuning_vector_draws}
        inputs = {f"vector {i}": draws[d]["vector"] for i, d in enumerate(s.tuning_vector_draws)}
        mean = submit(mean_vector_task, "tuning mean capability vector γ̄_tune", inputs, {})
        return dict.fromkeys(tunes, mean)
    return {
        t: submit(
            extract_task,
            _seeded("tuning capability vector γ", t, tunes),
            {
                "minuend": extraction["auxiliary"][t],
                "subtrahend": extraction["standard"][t],
                "base": base["pretrained"],
            },
            cfg.vector,
        )
        for t in tunes
    }


def _tune_alpha_lambda(study: _Study, base: dict[str, Any], extraction: dict[str, Any]) -> str:
    """CapVector's α × λ, chosen on validation goals from runs at the tuning seeds; the selection's id."""
    cfg, s, submit, tunes = study.cfg, study.cfg.study, study.submit, study.cfg.study.tuning_seeds
    vectors = _tuning_vectors(study, base, extraction)
    shared = len(set(map(id, vectors.values()))) == 1 and len(tunes) > 1
    grid_cells = []
    for alpha in s.alphas:
        merged: dict[int, Any] = {}
        for t in tunes:
            if shared and merged:
                merged[t] = next(iter(merged.values()))
                continue
            label = f"tune merge θ_meta α={alpha}"
            label = label if shared else _seeded(label, t, tunes)
            merge_inputs = {"base": base["pretrained"], "vector": vectors[t]}
            merged[t] = submit(merge_task, label, merge_inputs, cfg.merge_config(alpha))
        lambdas = [("lambda_scale", x, f"λ={x}") for x in s.lambda_scales]
        lambdas += [("lambda_absolute", x, f"λ_abs={x:g}") for x in s.lambdas]
        for form, value, name in lambdas:
            what = f"capvector α={alpha} {name}"
            evaluations = []
            for t in tunes:
                run = submit_arm(
                    study.steps,
                    {**base, "vector": vectors[t]},
                    "capvector",
                    t,
                    cfg.study_downstream("capvector", t, **{form: value}),
                    label=_seeded(f"tune {what}", t, tunes),
                    meta=merged[t],
                )
                evaluations += study.validate_curve(run, _seeded(what, t, tunes))
            grid_cells.append(({"alpha": alpha, form: value}, evaluations))
    return study.select("α and λ", grid_cells, {"seeds": tunes, "endpoint": cfg.curve_budgets})


def _merges(study: _Study, d: int, stage: dict, base: dict[str, Any], selection: str, alpha: float) -> None:
    """A unit's θ_meta and θ_null at the chosen α (and its dose θ_meta where the arm runs)."""
    cfg, submit = study.cfg, study.submit
    merges = [("meta", "vector", "θ_meta", alpha), ("null_meta", "null_vector", "θ_null", alpha)]
    if "meta_sft_dose" in cfg.study.arms:
        merges.append(("dose_meta", "vector", f"θ_meta α={cfg.study.dose_alpha}", cfg.study.dose_alpha))
    for which, vector, name, coefficient in merges:
        merge_inputs = {"base": base["pretrained"], "vector": stage[vector], "selection": selection}
        label = f"{study.unit} {d} merge {name}"
        stage[which] = submit(merge_task, label, merge_inputs, cfg.merge_config(coefficient))
    meta_validation = submit(
        evaluate_task,
        f"validate {study.unit} {d} θ_meta on D_ext",
        {"checkpoint": stage["meta"]},
        study.validation_ext,
    )
    study.record(ExtractionValidation(which="meta", draw=d), meta_validation)


AFTER_GATE_ARMS = ("meta_sft", "meta_sft_dose", "capvector", "null_capvector")
START_NAMES = {"meta": "θ_meta", "null_meta": "θ_null", "dose_meta": "θ_meta dose"}


def _capvector_arms(
    study: _Study, units: dict, base: dict[str, Any], selection: str, chosen_values: dict, runs: dict
) -> list[str]:
    """Each unit's θ_meta, θ_null (and dose), then the arms that start from them; the arms run."""
    cfg = study.cfg
    rest = [arm for arm in AFTER_GATE_ARMS if arm in cfg.study.arms]
    lam = {k: chosen_values[k] for k in ("lambda_scale", "lambda_absolute") if k in chosen_values}
    for d, stage in units.items():
        _merges(study, d, stage, base, selection, chosen_values["alpha"])
        for arm in rest:
            init = ARMS[arm].init
            study.test_start(stage[init], arm, d, f"{study.unit} {d} {START_NAMES[init]}")
            for seed in cfg.seeds:
                step = cfg.study_downstream(arm, seed, **(lam if ARMS[arm].orthogonal else {}))
                runs[arm, d, seed] = study.train_draw_arm(stage, arm, d, seed, step, selection)
    return rest


def _run_study(study: _Study) -> dict[str, Any]:
    """The study in order: the gate's arms, the gate, then CapVector's α × λ and arms (see the module)."""
    cfg, s = study.cfg, study.cfg.study
    base = _foundations(study)
    runs: dict[tuple[str, int, int], Any] = {}  # (arm, draw, seed) -> checkpoint
    for seed in cfg.seeds:
        step = cfg.study_downstream("sft", seed)
        runs["sft", SHARED, seed] = submit_arm(study.steps, base, "sft", seed, step)
    aux_grid = _aux_grid(study, base)
    for arm in [a for a in SHARED_ARMS if a in s.arms]:
        study.test_start(base["pretrained"], arm, SHARED, "θ_pt")

    extraction = _extraction(study, base["data"], base["pretrained"])
    draws = {d: _draw(study, d, base, extraction) for d in s.draws}
    units = _units(study, draws)
    chosen_values = {"extraction_lr": extraction["lr"], "extraction_aux_weight": extraction["aux_weight"]}
    if aux_grid:
        _aux_runs(study, base, aux_grid, runs, chosen_values)
    _gate_arms(study, units, runs)
    study.test_runs({k: v for k, v in runs.items() if k[0] in GATE_ARMS})
    _held_out_losses(study, draws, base["data"]["heldout"])
    if s.gate:
        gate_report = study.analyse("gate", _design(cfg, chosen_values))
        if s.gate_only:
            emit(f"[study {cfg.name}] gate-only study: it ends at its gate, and its report is the gate's")
            return {"report": gate_report, "selections": _selections(study)}
        if not study.gate_passed(gate_report):
            emit(f"[study {cfg.name}] gate: preconditions (c), (c′) not shown; CapVector's arms are not run")
            return {"report": gate_report, "selections": _selections(study)}
        if study.gate_more:
            after_gate(study.steps, study.gate_more)

    selection = _tune_alpha_lambda(study, base, extraction)
    best = study.chosen(selection)
    chosen_values |= {k: best[k] for k in ("alpha", "lambda_scale", "lambda_absolute") if k in best}
    if s.dose_alpha is not None:
        chosen_values["dose_alpha"] = s.dose_alpha
    rest = _capvector_arms(study, units, base, selection, chosen_values, runs)
    study.test_runs({k: v for k, v in runs.items() if k[0] in rest})
    report = study.analyse("final", _design(cfg, chosen_values))
    return {"report": report, "selections": _selections(study)}


def _selections(study: _Study) -> dict[str, str]:
    return {k: resolve(v) for k, v in study.analysis_inputs.items() if k.startswith("selection")}


def _design(cfg: StudyConfig, chosen_values: dict[str, float]) -> dict[str, Any]:
    """What the analysis needs besides the evaluations (capvector.tasks.steps.study_analysis.StudyDesign)."""
    s = cfg.study
    return {
        "name": cfg.name,
        "arms": list(s.arms),
        "draws": list(s.draws),
        "seeds": list(cfg.seeds),
        "endpoint_budgets": cfg.curve_budgets,
        "final_budget": cfg.downstream.steps,
        "extraction_steps": cfg.extraction.steps,
        "flat_tolerance": s.flat_tolerance,
        "non_inferiority_margin": s.non_inferiority_margin,
        "n_boot": s.n_boot,
        "gate": s.gate,
        "draws_per_replicate": s.draws_per_replicate,
        "chosen": chosen_values,
        "grids": {
            "extraction_lr": list(s.extraction_lrs),
            "extraction_aux_weight": list(s.extraction_aux_weights),
            "aux_weight": list(s.aux_weights),
            "alpha": list(s.alphas),
            "lambda_scale": list(s.lambda_scales),
            "lambda_absolute": list(s.lambdas),
        },
    }


def plan_study(cfg: StudyConfig, steps: StepRunner) -> dict[str, Any]:
    """Submit the study's steps to `steps` (a flow's runner, or a CacheProbe): the report's and the
    selections' ids, and the report in Markdown."""
    workspace = workspace_for(steps.home)
    study = _Study(cfg, steps, workspace)
    study.gate_more = study_steps(cfg)[1]
    ids = _run_study(study)
    return {**ids, "markdown": study_markdown(workspace, load_study_report(workspace, ids["report"]))}
