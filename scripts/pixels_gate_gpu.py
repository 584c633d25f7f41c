"""The pixels study's gate phase in one command, sized for a borrowed GPU machine (no Prefect there).

The study flow needs Prefect, DuckDB and a catalogue; a lent GPU machine has none of them and is held
for minutes. This script runs the same recipe's gate phase from `capvector_core` alone: pixels
observations (64×64 corner2 images + proprioception), the `spatial_depth` objective (or, with
`--objective spatial`, the 9-d hand/object/goal xyz targets), the control study's calibrated splits
(or, with `--tasks hard`, `study-control-hard`'s), and the four arms the gate needs (SFT, auxiliary
SFT, SFT from θ_ao, SFT from θ_ft), plus θ_ao vs θ_ft on D_ext validation goals (precondition b)
and their held-out action loss at half and full length (precondition a). With `--observation
state_features` it runs the control studies' testbed instead (state through random features, the
`spatial` objective) with the larger policy. `--train-procs` runs that many small, Python-bound
trainings at once on the GPU, while a process pool rolls out each finished checkpoint on the CPUs. Every
episode is appended to `<out>/episodes.jsonl` as it finishes (a run cut short still returns what it
measured); `docs/studies/` is written from those records on a workstation by `scripts/pixels_gate_report.py`.

Nothing is chosen here: every value (aux weight 0.5, lr, budgets) is declared below or on the command
line before a rollout; with several `--aux-weights` the report chooses one on validation goals.

    MUJOCO_GL=egl python scripts/pixels_gate_gpu.py --out /tmp/gate --scale tiny   # a CPU dry run
"""

from __future__ import annotations

import argparse
import json
import os
import time
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path

import torch

from capvector.core.evaluation.rollouts import EvalConfig, evaluate
from capvector.core.policies.base import build_policy, load_policy
from capvector.core.simulation.demos import (
    UNIT_SEEDS,
    VALIDATION_SEED_BASE,
    DemoConfig,
    DemoDataset,
    collect_demos,
)
from capvector.core.training.held_out_loss import held_out_action_loss
from capvector.core.training.trainer import AuxConfig, TrainConfig, train

PRETRAIN = [
    "reach-v3",
    "push-v3",
    "pick-place-v3",
    "door-open-v3",
    "drawer-open-v3",
    "button-press-topdown-v3",
    "window-open-v3",
    "plate-slide-v3",
]
EXTRACTION = [
    "button-press-v3",
    "faucet-open-v3",
    "handle-press-v3",
    "door-close-v3",
    "faucet-close-v3",
    "door-unlock-v3",
]
DOWNSTREAM = [
    "plate-slide-side-v3",
    "drawer-close-v3",
    "handle-press-side-v3",
    "button-press-wall-v3",
    "coffee-button-v3",
    "window-close-v3",
    "plate-slide-back-v3",
]
# `study-control-hard`'s splits (its preset states the rule): the six calibrated tasks with the lowest
# SFT mean downstream, the other nine to extraction.
HARD_EXTRACTION = [
    "faucet-close-v3",
    "handle-press-side-v3",
    "coffee-button-v3",
    "button-press-v3",
    "button-press-wall-v3",
    "faucet-open-v3",
    "handle-press-v3",
    "drawer-close-v3",
    "plate-slide-side-v3",
]
HARD_DOWNSTREAM = [
    "dial-turn-v3",
    "door-unlock-v3",
    "door-lock-v3",
    "door-close-v3",
    "plate-slide-back-v3",
    "window-close-v3",
]
TASK_SETS = {"calibrated": (EXTRACTION, DOWNSTREAM), "hard": (HARD_EXTRACTION, HARD_DOWNSTREAM)}

SCALES = {
    "gpu": dict(
        pretrain=PRETRAIN,
        extraction=EXTRACTION,
        downstream=DOWNSTREAM,
        episodes=(10, 10, 5),
        horizon=500,
        batch=64,
        pretrain_steps=2000,
        extraction_steps=1000,
        downstream_steps=400,
        budgets=[100, 200, 400],
        draws=[0, 1],
        seeds=[0, 1, 2],
        test_goals=20,
        validation_goals=10,
        eval_horizon=150,
    ),
    "tiny": dict(
        pretrain=PRETRAIN[:2],
        extraction=EXTRACTION[:1],
        downstream=DOWNSTREAM[:1],
        episodes=(1, 1, 1),
        horizon=150,
        batch=16,
        pretrain_steps=6,
        extraction_steps=4,
        downstream_steps=4,
        budgets=[2, 4],
        draws=[0],
        seeds=[0],
        test_goals=2,
        validation_goals=2,
        eval_horizon=12,
    ),
}
POLICY = {
    "obs_mode": "pixels",
    "image_size": 64,
    "d_model": 128,
    "n_layers": 4,
    "n_heads": 4,
    "chunk_size": 8,
}
# `--observation state_features`: the control studies' testbed (state through 128 random sine features
# plus 32 high-frequency goal distractors, docs/studies/calibration.md) with the larger policy of
# docs/studies/study_control_small_large*.md.
STATE_POLICY = {
    "obs_mode": "state",
    "d_model": 128,
    "n_layers": 4,
    "n_heads": 4,
    "chunk_size": 8,
    "obs_transform": {"kind": "random_features"},
}
AUX = AuxConfig(name="spatial_depth", weight=0.5)
HELDOUT_EPISODES = 3  # held-out demos per extraction task: precondition (a), as the study measures it


def train_config(
    steps: int,
    batch: int,
    seed: int,
    aux: AuxConfig | None,
    snapshots: list[int] = (),
    lr: float = 1e-3,
) -> TrainConfig:
    """The study presets' optimizer (AdamW, lr 1e-3, batch 64); the device is whatever the machine has."""
    return TrainConfig(
        steps=steps,
        batch_size=batch,
        lr=lr,
        warmup_steps=min(50, steps // 10),
        seed=seed,
        aux=aux,
        checkpoint_every=steps,
        snapshot_steps=list(snapshots),
        device="auto",
        num_threads=1,
    )


def train_job(
    name: str, policy: dict, init: str | None, data: str, config: dict, work: str, heldout: str | None
):
    """One training run (in a training-pool process, sharing the GPU with the others).

    Returns its checkpoints by step and its speed; with `heldout`, also the held-out action loss at
    each checkpoint (precondition (a): flat over the second half)."""
    torch.set_num_threads(1)
    config = TrainConfig.model_validate(config)
    torch.manual_seed(config.seed)
    model = build_policy(policy, device="auto") if init is None else load_policy(init, device="auto")
    result = train(model, DemoDataset.load(data), config, Path(work) / name)
    paths = {**{b: str(p) for b, p in result.snapshots.items()}, config.steps: str(result.weights_path)}
    summary = {
        "steps_per_s": result.steps_per_s,
        "final_loss": result.final_loss,
        "device": result.execution.get("device"),
    }
    if heldout is not None:
        held = DemoDataset.load(heldout)
        summary["heldout_loss"] = {
            b: held_out_action_loss(p, held, 256, 0, device="auto") for b, p in sorted(paths.items())
        }
    return name, paths, summary


def rollouts(path: str, config: dict, labels: dict) -> list[dict]:
    """One checkpoint's episodes (in a pool worker, on one CPU thread): rows for the analysis."""
    torch.set_num_threads(1)
    policy = load_policy(path, device="cpu").eval()
    result = evaluate(policy.predict_action_chunk, EvalConfig.model_validate(config))
    base = config["seed_base"]
    return [
        {**labels, "task": e.task, "goal": e.seed - base, "success": int(e.success), "steps": e.steps}
        for e in result.episodes
    ]


class Episodes:
    """Submits evaluations to the pool and appends each one's rows to episodes.jsonl as it returns."""

    def __init__(self, out: Path, pool: ProcessPoolExecutor, observation: dict):
        self.path, self.pool, self.observation, self.pending = out / "episodes.jsonl", pool, observation, []

    def submit(
        self, path: str, tasks: list[str], goals: int, seed_base: int, horizon: int, split="test", **labels
    ) -> None:
        config = {
            "tasks": tasks,
            "episodes_per_task": goals,
            "seed_base": seed_base,
            "horizon": horizon,
            "execute_steps": 4,
            "batch_size": 35,
            **self.observation,
        }
        future = self.pool.submit(rollouts, str(path), config, {"split": split, **labels})
        future.add_done_callback(self._append)
        self.pending.append(future)

    def _append(self, future: Future) -> None:
        rows = future.result()
        with self.path.open("a") as f:
            f.writelines(json.dumps(r) + "\n" for r in rows)
        print(
            f"[{stamp()}] evaluated {rows[0]['arm']} draw {rows[0]['draw']} seed {rows[0]['seed']} "
            f"@ {rows[0]['budget']}: {100 * sum(r['success'] for r in rows) / len(rows):.1f} %",
            flush=True,
        )

    def wait(self) -> None:
        for future in self.pending:
            future.result()


START = time.perf_counter()


def stamp() -> str:
    return f"{time.perf_counter() - START:6.1f} s"


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--work", type=Path, default=Path("/tmp/pixels-gate"))
    ap.add_argument("--scale", choices=sorted(SCALES), default="gpu")
    ap.add_argument("--workers", type=int, help="evaluation processes (default: the CPUs the trainers leave)")
    ap.add_argument("--train-procs", type=int, default=1, help="training runs at once, sharing the GPU")
    ap.add_argument(
        "--observation",
        choices=["pixels", "state_features"],
        default="pixels",
        help="64×64 pixels, or the control studies' state through random features (objective `spatial`)",
    )
    ap.add_argument(
        "--downstream-episodes", type=int, help="demos per downstream task (default: the scale's)"
    )
    ap.add_argument("--aux-weights", type=float, nargs="+", default=[AUX.weight], help="aux arms' weights")
    ap.add_argument("--extraction-aux-weight", type=float, default=AUX.weight, help="θ_ao's aux weight")
    ap.add_argument("--extraction-steps", type=int, help="θ_ft / θ_ao steps (default: the scale's)")
    ap.add_argument("--extraction-lr", type=float, default=1e-3, help="θ_ft / θ_ao learning rate")
    ap.add_argument("--downstream-steps", type=int, help="final budget; the others at 1/4 and 1/2 of it")
    ap.add_argument("--seeds", type=int, nargs="+", help="downstream training seeds (default: the scale's)")
    ap.add_argument("--draws", type=int, nargs="+", help="γ draws (default: the scale's)")
    ap.add_argument("--test-goals", type=int, help="test goals per downstream task (default: the scale's)")
    ap.add_argument("--no-extraction", action="store_true", help="only SFT and the auxiliary arm(s)")
    ap.add_argument(
        "--objective",
        choices=["spatial_depth", "spatial"],
        default=AUX.name,
        help="per-patch depth (Spatial Forcing's analogue) or the 9-d hand/object/goal xyz",
    )
    ap.add_argument(
        "--tasks", choices=sorted(TASK_SETS), default="calibrated", help="extraction and downstream task sets"
    )
    args = ap.parse_args()
    if args.scale == "tiny" and args.tasks != "calibrated":
        ap.error("--scale tiny has its own two-task splits; --tasks applies to --scale gpu")
    if args.observation == "state_features" and args.objective != "spatial":
        ap.error("--observation state_features has no depth render: use --objective spatial")
    if args.work.exists() and any(args.work.iterdir()):
        ap.error(f"--work {args.work} holds an earlier run's files: pass a new folder")
    if args.workers is None:
        args.workers = max(1, (os.cpu_count() or 2) - args.train_procs - 1)
    return args


def settings(args: argparse.Namespace) -> dict:
    """The scale's sizes, with what the command line overrides."""
    s = dict(SCALES[args.scale])
    if args.downstream_steps:
        steps = args.downstream_steps
        s.update(downstream_steps=steps, budgets=[steps // 4, steps // 2, steps])
    for key in ("seeds", "draws", "test_goals", "extraction_steps"):
        s[key] = getattr(args, key) or s[key]
    if args.scale != "tiny":
        s["extraction"], s["downstream"] = TASK_SETS[args.tasks]
    s["down_episodes"] = args.downstream_episodes or s["episodes"][2]
    return s


def collect(
    args: argparse.Namespace, s: dict, observation: dict, split: str, tasks: list[str], **demo
) -> str:
    """Collects a split (`demo`: episodes_per_task, patch_xyz, seed_offset) and saves it under the work
    folder, where training processes load it."""
    t = time.perf_counter()
    workers = args.workers + args.train_procs
    data = collect_demos(
        DemoConfig(tasks=tasks, horizon=s["horizon"], workers=workers, patch_grid=4, **demo, **observation)
    )
    print(f"[{stamp()}] demos {split}: {len(data)} frames in {time.perf_counter() - t:.1f} s", flush=True)
    return str(data.save(args.work / "data" / split, overwrite=True))


def collect_splits(
    args: argparse.Namespace, s: dict, observation: dict, depth: bool
) -> dict[str, str | None]:
    """pretrain, extraction, its held-out episodes and downstream: each split's saved folder (None for
    the extraction splits with --no-extraction). Per-patch xyz only where the objective reads it."""
    pre_n, ext_n, _ = s["episodes"]
    splits: dict[str, str | None] = {
        "pretrain": collect(args, s, observation, "pretrain", s["pretrain"], episodes_per_task=pre_n),
        "extraction": None,
        "heldout": None,
    }
    if not args.no_extraction:
        ext = dict(episodes_per_task=ext_n, patch_xyz=depth)
        splits["extraction"] = collect(args, s, observation, "extraction", s["extraction"], **ext)
        offset = DemoConfig(tasks=s["extraction"], episodes_per_task=ext_n).n_units * UNIT_SEEDS
        held = dict(episodes_per_task=HELDOUT_EPISODES, patch_xyz=depth, seed_offset=offset)
        splits["heldout"] = collect(args, s, observation, "heldout", s["extraction"], **held)
    down = dict(episodes_per_task=s["down_episodes"], patch_xyz=depth)
    splits["downstream"] = collect(args, s, observation, "downstream", s["downstream"], **down)
    return splits


class Trainings:
    """Trains jobs (name, init, data, config, heldout) in the training pool, keeping each run's summary."""

    def __init__(self, pool: ProcessPoolExecutor, policy: dict, work: Path):
        self.pool, self.policy, self.work, self.runs = pool, policy, work, {}

    def fit_all(self, jobs: list[tuple], on_done) -> None:
        """Every job to the pool at once; `on_done(name, {step: checkpoint path})` as each one finishes."""
        futures = [
            self.pool.submit(
                train_job, name, self.policy, init, data, config.model_dump(), str(self.work), held
            )
            for name, init, data, config, held in jobs
        ]
        for future in as_completed(futures):
            name, paths, summary = future.result()
            self.runs[name] = summary
            print(
                f"[{stamp()}] trained {name}: {summary['steps_per_s']:.1f} steps/s, "
                f"loss {summary['final_loss']:.4f}"
                + (f", held-out {summary['heldout_loss']}" if "heldout_loss" in summary else ""),
                flush=True,
            )
            on_done(name, paths)


def goal_sets(s: dict) -> dict[str, dict]:
    """Where each evaluation's goals come from: D_down test goals, D_ext and D_down validation goals."""
    horizon = s["eval_horizon"]
    valid = dict(tasks=s["extraction"], goals=s["validation_goals"], seed_base=VALIDATION_SEED_BASE)
    return {
        "test": dict(tasks=s["downstream"], goals=s["test_goals"], seed_base=100_000, horizon=horizon),
        "valid": dict(valid, horizon=horizon, split="validation"),
        "valid_down": dict(valid, tasks=s["downstream"], horizon=horizon, split="validation"),
    }


def extract(
    args, s: dict, trainings: Trainings, episodes: Episodes, splits: dict, starts: dict, aux_base
) -> None:
    """θ_ft^d and θ_ao^d for each draw: the same θ_pt, seed and batch order; snapshots at half for (a);
    each final checkpoint rolled out on D_ext validation goals. Their paths go into `starts`."""
    ext_steps, valid = s["extraction_steps"], goal_sets(s)["valid"]
    ao = aux_base.model_copy(update={"weight": args.extraction_aux_weight})
    extraction = [
        (f"{arm}{draw}", starts["pt"], splits["extraction"], config, splits["heldout"])
        for draw in ([] if splits["extraction"] is None else s["draws"])
        for arm, aux in (("ft", None), ("ao", ao))
        for config in [train_config(ext_steps, s["batch"], draw, aux, [ext_steps // 2], args.extraction_lr)]
    ]

    def extracted(name: str, paths: dict) -> None:
        starts[name] = paths[ext_steps]
        episodes.submit(paths[ext_steps], **valid, arm=name[:2], draw=int(name[2:]), seed=0, budget=0)

    trainings.fit_all(extraction, extracted)


def fine_tune(
    args, s: dict, trainings: Trainings, episodes: Episodes, down: str, starts: dict, aux_base
) -> None:
    """The downstream arms on every seed: SFT and the auxiliary arm(s) from θ_pt, SFT from each θ_ft^d and
    θ_ao^d (each start rolled out once), every budget's snapshot rolled out on test goals (and, to
    choose among several aux weights, the aux arms' on D_down validation goals)."""
    goals = goal_sets(s)
    aux_arms = [
        ("aux" if len(args.aux_weights) == 1 else f"aux@{w:g}", aux_base.model_copy(update={"weight": w}))
        for w in args.aux_weights
    ]
    inits = [("sft", -1, starts["pt"], None)] + [(arm, -1, starts["pt"], aux) for arm, aux in aux_arms]
    inits += [
        (f"sft_from_{name[:2]}", int(name[2:]), path, None) for name, path in starts.items() if name != "pt"
    ]
    for arm, draw, init, _ in inits:
        if arm.startswith("sft_from"):
            episodes.submit(init, **goals["test"], arm=arm, draw=draw, seed=0, budget=0)
    labels, downstream = {}, []
    for arm, draw, init, aux in inits:
        for seed in s["seeds"]:
            name = f"{arm}-d{draw}-s{seed}"
            labels[name] = dict(arm=arm, draw=draw, seed=seed)
            config = train_config(s["downstream_steps"], s["batch"], seed, aux, s["budgets"][:-1])
            downstream.append((name, init, down, config, None))

    def finetuned(name: str, paths: dict) -> None:
        label = labels[name]
        for budget, path in paths.items():
            episodes.submit(path, **goals["test"], **label, budget=budget)
            if len(aux_arms) > 1 and label["draw"] == -1:  # the aux weight is chosen on validation goals
                episodes.submit(path, **goals["valid_down"], **label, budget=budget)

    trainings.fit_all(downstream, finetuned)


def write_runs(args, s: dict, policy: dict, aux_base, runs: dict) -> None:
    """runs.json: the settings every number came from, and each training run's summary."""
    record = {
        "scale": args.scale,
        "observation": args.observation,
        "settings": {k: v for k, v in s.items() if k != "down_episodes"},
        "policy": policy,
        "aux": aux_base.model_dump(),
        "tasks": args.tasks,
        "aux_weights": args.aux_weights,
        "extraction_aux_weight": args.extraction_aux_weight,
        "extraction_lr": args.extraction_lr,
        "downstream_episodes": s["down_episodes"],
        "train_procs": args.train_procs,
        "runs": runs,
        "wall_s": time.perf_counter() - START,
        "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
    }
    (args.out / "runs.json").write_text(json.dumps(record, indent=1, default=str))


def main() -> None:
    args = parse_args()
    s = settings(args)
    pixels = args.observation == "pixels"
    policy = POLICY if pixels else STATE_POLICY
    observation = {"obs_mode": "pixels", "image_size": 64} if pixels else {"obs_mode": "state"}
    aux_base = AUX.model_copy(update={"name": args.objective})
    depth = args.objective == "spatial_depth"  # per-patch xyz is only rendered when its objective reads it
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "episodes.jsonl").unlink(missing_ok=True)
    splits = collect_splits(args, s, observation, depth)
    with (
        ProcessPoolExecutor(args.workers, mp_context=get_context("spawn")) as pool,
        ProcessPoolExecutor(args.train_procs, mp_context=get_context("spawn")) as trainer_pool,
    ):
        episodes = Episodes(args.out, pool, observation)
        trainings = Trainings(trainer_pool, policy, args.work)
        starts: dict[str, str] = {}
        pt_steps = s["pretrain_steps"]
        trainings.fit_all(
            [("pt", None, splits["pretrain"], train_config(pt_steps, s["batch"], 0, None), None)],
            lambda name, paths: starts.update(pt=paths[pt_steps]),
        )
        episodes.submit(starts["pt"], **goal_sets(s)["test"], arm="pt", draw=-1, seed=0, budget=0)
        extract(args, s, trainings, episodes, splits, starts, aux_base)
        fine_tune(args, s, trainings, episodes, splits["downstream"], starts, aux_base)
        left = sum(not f.done() for f in episodes.pending)
        print(f"[{stamp()}] training done; waiting for {left} evaluations", flush=True)
        episodes.wait()
    write_runs(args, s, policy, aux_base, trainings.runs)
    print(f"[{stamp()}] done", flush=True)


if __name__ == "__main__":
    main()
