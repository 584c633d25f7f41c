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

A sweep (`study.sweep_arm`, `capvector sweep`: capvector.flows.study.recipe.sweep_study) is this plan up to
its α × λ choice and no further: demos, θ_pt, its one draw's θ_ft, θ_ao and γ (extraction values given),
the arm's α × λ cells at the tuning seeds and the `select` step, whose id is its result.
"""

from __future__ import annotations

from typing import Any

from capvector.flows.recipe.config import ARMS, lambda_label
from capvector.flows.recipe.plan import submit_arm
from capvector.flows.runtime.step_submission import CacheProbe, PlannedStep, PlanRecorder, StepRunner, resolve
from capvector.flows.study.config import GATE_ARMS, SHARED_ARMS, StudyConfig
from capvector.flows.study.report import load_study_report, study_markdown, sweep_markdown
from capvector.tasks.runtime.progress import emit
from capvector.tasks.runtime.workspace import Workspace, workspace_for
from capvector.tasks.steps.data import collect_demos_task
from capvector.tasks.steps.evaluation import evaluate_task
from capvector.tasks.steps.held_out_loss import held_out_loss_task
from capvector.tasks.steps.selection import chosen, select_task
from capvector.tasks.steps.study_analysis import analyse_study_task, gate_passed
from capvector.tasks.steps.training import LAMBDA_FORMS, snapshots_of, train_task
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


class Given(dict):
    """A grid's one value where nothing is chosen (`study.tuning_seeds` empty): no `select` step ran,
    so the runs that use it have no selection input."""


def _selected(selection: Any) -> Any:
    """A selection as a step input: None for a given value (there is no step to point at)."""
    return None if isinstance(selection, Given) else selection


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


def _start_kind(cfg: StudyConfig, arm: str) -> str:
    """Which checkpoint an arm's run starts from (runs starting alike share their budget-0 test); a
    variant starts where its arm does."""
    variant = cfg.study.variants.get(arm)
    return ARMS[variant.arm if variant else arm].init


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
        self.base: dict[str, Any] = {}
        self.units: dict[int, dict[str, Any]] = {}
        self.runs: dict[tuple[str, int, int], Any] = {}
        """What the study made, kept for `products`: demos and θ_pt, each unit's stage, the compared runs."""

    def submit(self, task: Any, step: str, inputs: dict[str, Any], config: Any) -> Any:
        inputs = {k: v for k, v in inputs.items() if not isinstance(v, Given)}
        return self.steps.submit(task, step, inputs, config if isinstance(config, dict) else _dump(config))

    def record(self, key: InputKey, value: Any) -> None:
        """An input of the study's analysis, under its typed key (capvector.tasks.study_inputs)."""
        self.analysis_inputs[key.key] = value

    def snapshots(self, run: Any) -> dict[int, str]:
        """Budget -> the checkpoint a run kept after that many steps (waits for the run)."""
        return snapshots_of(self.workspace, resolve(run))

    def chosen(self, selection: str | Given) -> dict[str, Any]:
        """The values a selection chose (or the given ones)."""
        return dict(selection) if isinstance(selection, Given) else chosen(self.workspace, selection)

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
        return submit_arm(self.steps, stage, arm, seed, step, label=label, selection=_selected(selection))

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
    ) -> str | Given:
        """A `select` step over (values, validation evaluations) cells — a cell's score is the mean over
        its evaluations — ties broken by the `tiebreaks` (held-out loss measurements, one per cell)
        when given; its id (waits for it). Where nothing is chosen, the one cell's values, given."""
        if not self.cfg.study.chooses:
            ((values, _),) = cells
            return Given(values)
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
        key = (_start_kind(self.cfg, arm), draw)
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

    def products(self) -> dict[str, Any]:
        """The ids of what the study made, by name: `datasets`, `pretrained`; per unit (draw or replicate)
        its θ_ft, θ_ao, γ and θ_meta (`standard`, `auxiliary`, `vector`, `meta`: at the top for a study of
        one unit, under `units` otherwise); every compared run's final checkpoint and its test
        evaluation (`checkpoints`, `evaluations`: `arm/seedS`, or `arm/<unit>D/seedS` with several units)."""
        out: dict[str, Any] = {
            "datasets": {k: resolve(v) for k, v in self.base.get("data", {}).items()},
            "pretrained": resolve(self.base.get("pretrained")),
        }
        names = ("standard", "auxiliary", "vector", "meta")
        units = {d: {k: resolve(u[k]) for k in names if k in u} for d, u in self.units.items()}
        if len(units) == 1:
            out |= next(iter(units.values()))
        elif units:
            out["units"] = {str(d): u for d, u in units.items()}
        final = self.cfg.downstream.steps
        out["checkpoints"], out["evaluations"] = {}, {}
        for (arm, d, seed), run in self.runs.items():
            unit = "" if d == SHARED or len(units) == 1 else f"{self.unit}{d}/"
            label = f"{arm}/{unit}seed{seed}"
            out["checkpoints"][label] = resolve(run)
            test = self.analysis_inputs.get(TestEvaluation(arm=arm, draw=d, seed=seed, budget=final).key)
            if test is not None:
                out["evaluations"][label] = resolve(test)
        return out

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

    def chosen(self, selection: PlannedStep | Given) -> dict[str, Any]:
        if isinstance(selection, Given):
            return dict(selection)
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
    ao_configs = {w: {t: cfg.extraction_run(True, t, lr, w) for t in tunes} for w in s.extraction_aux_weights}
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
    """Demonstrations and θ_pt: what every run starts from (`data`, `pretrained`); D_ext's demos and θ_pt's
    D_ext validation only where an arm needs γ; the held-out demos and that validation, which only the
    analysis reads, not in a sweep."""
    cfg, submit, gamma = study.cfg, study.submit, study.cfg.study.needs_gamma
    analysed = cfg.study.sweep_arm is None
    splits = ("pretrain", "extraction", "downstream") if gamma else ("pretrain", "downstream")
    data = {s: submit(collect_demos_task, f"demos {s}", {}, cfg.demo_config(s)) for s in splits}
    if gamma and analysed:
        held_out = cfg.heldout_demo_config()
        data["heldout"] = submit(collect_demos_task, "demos extraction (held out)", {}, held_out)
    if analysed:
        study.heldout_downstream = submit(
            collect_demos_task, "demos downstream (held out)", {}, cfg.downstream_heldout_demo_config()
        )
    pretrained = submit(train_task, "pretrain θ_pt", {"data": data["pretrain"]}, cfg.pretrain_step())
    if gamma and analysed:
        validation = submit(
            evaluate_task, "validate θ_pt on D_ext", {"checkpoint": pretrained}, study.validation_ext
        )
        study.record(ExtractionValidation(which="pt", draw=SHARED), validation)
    study.record(Pretrained(), pretrained)
    return {"data": data, "pretrained": pretrained}


def _lr_grids(study: _Study, base: dict[str, Any]) -> dict[str, list[tuple[float, list[Any]]]]:
    """Arm -> [(lr, its tuning run at each tuning seed)]: full fine-tuning's (with `study.sft_lrs`) and
    every variant's, submitted at once (each is chosen later, at the endpoint, on validation goals)."""
    s, tunes = study.cfg.study, study.cfg.study.tuning_seeds
    lrs = ({"sft": s.sft_lrs} if s.sft_lrs else {}) | {name: v.lrs for name, v in s.variants.items()}
    return {
        name: [
            (
                lr,
                [
                    _shared_run(study, base, name, t, lr, _seeded(f"tune {name} lr={lr:g}", t, tunes))
                    for t in tunes
                ],
            )
            for lr in grid
        ]
        for name, grid in lrs.items()
    }


def _shared_run(
    study: _Study, base: dict[str, Any], name: str, seed: int, lr: float, label: str, selection: Any = None
) -> Any:
    """A run of full fine-tuning (`sft`) or of a variant at `seed` and `lr`."""
    cfg = study.cfg
    variant = cfg.study.variants.get(name)
    step = cfg.variant_downstream(name, seed, lr) if variant else cfg.sft_downstream(seed, lr)
    arm = variant.arm if variant else name
    return submit_arm(study.steps, base, arm, seed, step, label=label, selection=_selected(selection))


def _shared_runs(
    study: _Study, base: dict[str, Any], grids: dict[str, list], runs: dict, chosen_values: dict
) -> None:
    """Each lr grid's choice (validation goals, tuning seeds, the endpoint), then that arm's compared run
    at every seed with the selection as its input: full fine-tuning (when it has a grid) and each variant."""
    cfg, tunes = study.cfg, study.cfg.study.tuning_seeds
    for name, grid in grids.items():
        cells = [
            (
                {"lr": lr},
                [
                    e
                    for t, run in zip(tunes, tuning_runs, strict=True)
                    for e in study.validate_curve(run, _seeded(f"{name} lr={lr:g}", t, tunes))
                ],
            )
            for lr, tuning_runs in grid
        ]
        context = {"arm": name, "seeds": tunes, "endpoint": cfg.curve_budgets}
        selection = study.select(f"{name} lr", cells, context)
        lr = chosen_values[f"{name}_lr"] = study.chosen(selection)["lr"]
        for seed in cfg.seeds:
            label = f"downstream {name} seed {seed}"
            runs[name, SHARED, seed] = _shared_run(study, base, name, seed, lr, label, selection)


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
        runs["aux", SHARED, seed] = submit_arm(
            study.steps, base, "aux", seed, step, selection=_selected(aux_selection)
        )


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
    """Tuning seed -> the γ its α × λ runs use: a sweep's one draw's γ (`study.units`), the mean γ̄_tune
    of `study.tuning_vector_draws` (one for every tuning seed), else each tuning seed's own θ_ao − θ_ft
    from the extraction grid."""
    cfg, s, submit, tunes = study.cfg, study.cfg.study, study.submit, study.cfg.study.tuning_seeds
    if s.sweep_arm is not None:
        (stage,) = study.units.values()
        return dict.fromkeys(tunes, stage["vector"])
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
    """CapVector's α × λ (a sweep's: its arm's), chosen on validation goals from runs at the tuning seeds;
    the selection's id. An arm without the orthogonal loss has one λ cell per α: none."""
    cfg, s, submit, tunes = study.cfg, study.cfg.study, study.submit, study.cfg.study.tuning_seeds
    arm = s.sweep_arm or "capvector"
    lambdas = s.lambda_cells(cfg.orthogonal) if ARMS[arm].orthogonal else [{}]
    vectors = _tuning_vectors(study, base, extraction)
    grid_cells = []
    for alpha in s.alphas:
        label, merge = f"tune merge θ_meta α={alpha}", cfg.merge_config(alpha)
        if s.tuning_vector_draws or s.sweep_arm:  # one γ for every tuning seed: one θ_meta per α
            inputs = {"base": base["pretrained"], "vector": vectors[tunes[0]]}
            merged = dict.fromkeys(tunes, submit(merge_task, label, inputs, merge))
        else:
            pairs = {t: {"base": base["pretrained"], "vector": vectors[t]} for t in tunes}
            merged = {t: submit(merge_task, _seeded(label, t, tunes), pairs[t], merge) for t in tunes}
        for lam in lambdas:
            what = f"{arm} α={alpha} {lambda_label(lam)}"
            evaluations = []
            for t in tunes:
                run = submit_arm(
                    study.steps,
                    {**base, "vector": vectors[t]},
                    arm,
                    t,
                    cfg.study_downstream(arm, t, lam or None),
                    label=_seeded(f"tune {what}", t, tunes),
                    meta=merged[t],
                )
                evaluations += study.validate_curve(run, _seeded(what, t, tunes))
            grid_cells.append(({"alpha": alpha, **lam}, evaluations))
    context = {"seeds": tunes, "endpoint": cfg.curve_budgets} | ({"arm": arm} if s.sweep_arm else {})
    return study.select("α and λ", grid_cells, context)


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


AFTER_GATE_ARMS = (
    "meta_sft",
    "meta_sft_dose",
    "capvector",
    "null_capvector",
    "capvector_lora",
    "capvector_lora_sp",
    "capvector_adalora",
)
START_NAMES = {"meta": "θ_meta", "null_meta": "θ_null", "dose_meta": "θ_meta dose"}


def _capvector_arms(
    study: _Study, units: dict, base: dict[str, Any], selection: str, chosen_values: dict, runs: dict
) -> list[str]:
    """Each unit's θ_meta, θ_null (and dose), then the arms that start from them; the arms run."""
    cfg = study.cfg
    rest = [arm for arm in AFTER_GATE_ARMS if arm in cfg.study.arms]
    lam = {k: chosen_values[k] for k in LAMBDA_FORMS if k in chosen_values}
    for d, stage in units.items():
        _merges(study, d, stage, base, selection, chosen_values["alpha"])
        for arm in rest:
            init = ARMS[arm].init
            study.test_start(stage[init], arm, d, f"{study.unit} {d} {START_NAMES[init]}")
            for seed in cfg.seeds:
                step = cfg.study_downstream(arm, seed, lam if ARMS[arm].orthogonal else None)
                runs[arm, d, seed] = study.train_draw_arm(stage, arm, d, seed, step, selection)
    return rest


def _shared_study(study: _Study, base: dict[str, Any], grids: dict, aux_grid: list, runs: dict) -> dict:
    """A study whose arms need no γ (sft, aux, the variants): no extraction, no gate; every choice, the
    compared runs, their tests and the analysis."""
    chosen_values: dict[str, float] = {}
    if aux_grid:
        _aux_runs(study, base, aux_grid, runs, chosen_values)
    _shared_runs(study, base, grids, runs, chosen_values)
    study.test_runs(runs)
    report = study.analyse("final", _design(study.cfg, chosen_values))
    return {"report": report, "selections": _selections(study)}


def _sweep(study: _Study, base: dict[str, Any]) -> dict[str, Any]:
    """A sweep (`study.sweep_arm`): its one draw's θ_ft, θ_ao and γ with the given extraction values, then
    the arm's α × λ, chosen on validation goals (`_tune_alpha_lambda`); it ends at that selection."""
    s = study.cfg.study
    (d,) = s.draws
    (lr,), (weight,) = s.extraction_lrs, s.extraction_aux_weights
    given = {"lr": lr, "aux_weight": weight, "lr_selection": Given(lr=lr)}
    given["weight_selection"] = Given(aux_weight=weight)
    study.units = {d: _draw(study, d, base, given, compared=False)}
    selection = _tune_alpha_lambda(study, base, given)
    return {"sweep": selection, "selections": _selections(study)}


def _run_study(study: _Study) -> dict[str, Any]:
    """The study in order: the gate's arms, the gate, then CapVector's α × λ and arms (see the module);
    a sweep, its α × λ alone."""
    cfg, s = study.cfg, study.cfg.study
    base = study.base = _foundations(study)
    if s.sweep_arm is not None:
        return _sweep(study, base)
    runs = study.runs  # (arm, draw, seed) -> checkpoint
    grids = _lr_grids(study, base)
    for seed in cfg.seeds if "sft" not in grids else ():  # without a grid, at once
        step = cfg.study_downstream("sft", seed)
        runs["sft", SHARED, seed] = submit_arm(study.steps, base, "sft", seed, step)
    aux_grid = _aux_grid(study, base)
    for arm in [a for a in SHARED_ARMS if a in s.arms] + list(s.variants):
        study.test_start(base["pretrained"], arm, SHARED, "θ_pt")
    if not s.needs_gamma:
        return _shared_study(study, base, grids, aux_grid, runs)

    extraction = _extraction(study, base["data"], base["pretrained"])
    draws = {d: _draw(study, d, base, extraction) for d in s.draws}
    units = study.units = _units(study, draws)
    chosen_values = {"extraction_lr": extraction["lr"], "extraction_aux_weight": extraction["aux_weight"]}
    if aux_grid:
        _aux_runs(study, base, aux_grid, runs, chosen_values)
    _shared_runs(study, base, grids, runs, chosen_values)
    _gate_arms(study, units, runs)
    study.test_runs({k: v for k, v in runs.items() if k[0] in GATE_ARMS or k[0] in s.variants})
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
    chosen_values |= {k: best[k] for k in ("alpha", *LAMBDA_FORMS) if k in best}
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
        "arms": [*s.arms, *s.variants],
        "variants": {name: v.model_dump(mode="json") for name, v in s.variants.items()},
        "compare": [list(pair) for pair in s.compare],
        "draws": list(s.draws) if s.needs_gamma else [],
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
        **({} if s.chooses else {"given": True}),  # absent where values are chosen: those plans as they were
        "grids": {
            "extraction_lr": list(s.extraction_lrs),
            "extraction_aux_weight": list(s.extraction_aux_weights),
            "aux_weight": list(s.aux_weights),
            "alpha": list(s.alphas),
            "lambda_relative": list(s.lambdas_relative),
            "lambda_absolute": list(s.lambdas_absolute),
            **({"sft_lr": list(s.sft_lrs)} if s.sft_lrs else {}),
            **{f"{name}_lr": list(v.lrs) for name, v in s.variants.items()},
        },
    }


def plan_study(cfg: StudyConfig, steps: StepRunner) -> dict[str, Any]:
    """Submit the study's steps to `steps` (a flow's runner, or a CacheProbe): the report's (a sweep's:
    its selection's, `sweep`) and the selections' ids, and the report (the sweep's table) in Markdown."""
    workspace = workspace_for(steps.home)
    study = _Study(cfg, steps, workspace)
    study.gate_more = study_steps(cfg)[1]
    ids = _run_study(study)
    if "sweep" in ids:  # a sweep's result is its selection
        markdown = sweep_markdown(workspace.api.store.open_json(ids["sweep"]))
    else:
        markdown = study_markdown(workspace, load_study_report(workspace, ids["report"]))
    return {**ids, "products": study.products(), "markdown": markdown}
