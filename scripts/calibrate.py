"""Calibrate a testbed before a study: SFT learning curves per candidate task on validation goals.

A study can only answer its question on tasks where no endpoint sits at floor or ceiling. This script
pretrains θ_pt on the pretraining tasks, fine-tunes it on all candidate tasks together (multi-task,
as the study's downstream runs do) over `--seeds` pilot seeds, evaluates every kept budget on
validation goals (never the test goals), and applies the written rule

    mean success over the budgets within [--low, --high] and no seed's more than --spread points
    from the mean

to choose the tasks. With `--aux`, the auxiliary-objective arm is run beside SFT as a pilot of the
positive control (it is reported, never used by the rule). Writes JSON and Markdown to --out.

    python scripts/calibrate.py --out docs/calibration --aux spatial
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time
from pathlib import Path

import numpy as np
import torch

from capvector_core.demos import VALIDATION_SEED_BASE, DemoConfig, DemoDataset, collect_demos
from capvector_core.evaluation import EvalConfig, evaluate
from capvector_core.obs_transforms import ObsTransformConfig
from capvector_core.policy import build_policy, load_policy
from capvector_core.trainer import AuxConfig, TrainConfig, train

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
CANDIDATES = [
    "button-press-v3",
    "button-press-wall-v3",
    "coffee-button-v3",
    "dial-turn-v3",
    "door-close-v3",
    "door-lock-v3",
    "door-unlock-v3",
    "drawer-close-v3",
    "faucet-close-v3",
    "faucet-open-v3",
    "handle-press-v3",
    "handle-press-side-v3",
    "handle-pull-v3",
    "lever-pull-v3",
    "plate-slide-back-v3",
    "plate-slide-side-v3",
    "reach-wall-v3",
    "window-close-v3",
]


def cached_demos(config: DemoConfig, work: Path) -> DemoDataset:
    key = hashlib.sha256(config.model_dump_json(exclude={"workers"}).encode()).hexdigest()[:12]
    path = work / f"demos-{key}"
    if path.exists():
        return DemoDataset.load(path)
    dataset = collect_demos(config)
    dataset.save(path)
    return dataset


def pretrain_policy(policy_config: dict, demos: DemoDataset, steps: int, run_dir: Path) -> Path:
    """θ_pt for a pilot (seed 0, the study presets' pretraining settings); resumes from run_dir."""
    torch.manual_seed(0)
    policy = build_policy(policy_config, device="cpu")
    config = TrainConfig(
        steps=steps,
        batch_size=64,
        lr=1e-3,
        warmup_steps=100,
        checkpoint_every=500,
        num_threads=1,
        device="cpu",
    )
    return train(policy, demos, config, run_dir).weights_path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, default=Path("capvector_home/calibration"))
    ap.add_argument("--out", type=Path, default=Path("capvector_home/calibration/result"))
    ap.add_argument("--candidates", nargs="+", default=CANDIDATES)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--budgets", type=int, nargs="+", default=[50, 100, 200, 400])
    ap.add_argument("--episodes", type=int, default=5, help="demos per candidate task")
    ap.add_argument("--goals", type=int, default=10, help="validation goals per task")
    ap.add_argument("--pretrain-steps", type=int, default=1500)
    ap.add_argument("--transform", choices=["identity", "random_features"], default="random_features")
    ap.add_argument("--aux", default=None, help="also run this auxiliary objective (pilot; not in the rule)")
    ap.add_argument("--aux-weights", type=float, nargs="+", default=[0.5], help="one pilot arm per weight")
    ap.add_argument("--low", type=float, default=15.0)
    ap.add_argument("--high", type=float, default=85.0)
    ap.add_argument("--spread", type=float, default=40.0)
    args = ap.parse_args()
    torch.set_num_threads(1)
    args.work.mkdir(parents=True, exist_ok=True)
    transform = ObsTransformConfig(kind=args.transform)
    policy_config = {
        "obs_mode": "state",
        "d_model": 64,
        "n_layers": 2,
        "n_heads": 4,
        "chunk_size": 8,
        "obs_transform": transform.model_dump(),
    }
    start = time.perf_counter()
    pre = cached_demos(DemoConfig(tasks=PRETRAIN, episodes_per_task=10, horizon=500, workers=2), args.work)
    down = cached_demos(
        DemoConfig(tasks=args.candidates, episodes_per_task=args.episodes, horizon=500, workers=2), args.work
    )
    print(f"demos: {time.perf_counter() - start:.0f}s, failures {down.meta.failures}", flush=True)
    pt_path = pretrain_policy(
        policy_config, pre, args.pretrain_steps, args.work / f"pretrain-{args.transform}"
    )
    evaluation = EvalConfig(
        tasks=args.candidates,
        episodes_per_task=args.goals,
        seed_base=VALIDATION_SEED_BASE,
        horizon=150,
        execute_steps=4,
    )
    arms: dict[str, AuxConfig | None] = {"sft": None}
    for w in args.aux_weights if args.aux else []:
        arms[f"{args.aux} {w:g}"] = AuxConfig(name=args.aux, weight=w)
    curves: dict[str, dict[str, dict[int, dict[str, float]]]] = {}
    for arm, aux in arms.items():
        for seed in args.seeds:
            policy = load_policy(pt_path, device="cpu")
            config = TrainConfig(
                steps=max(args.budgets),
                batch_size=64,
                lr=1e-3,
                warmup_steps=20,
                seed=seed,
                checkpoint_every=100,
                num_threads=1,
                device="cpu",
                aux=aux,
                snapshot_steps=[b for b in args.budgets if b < max(args.budgets)],
            )
            tasks = "-".join(sorted(t.removesuffix("-v3") for t in args.candidates))
            key = hashlib.sha256(tasks.encode()).hexdigest()[:8]
            result = train(policy, down, config, args.work / f"{args.transform}-{key}-{arm}-{seed}")
            kept = {**result.snapshots, max(args.budgets): result.weights_path}
            for budget, path in sorted(kept.items()):
                rates = evaluate(
                    load_policy(path, device="cpu").predict_action_chunk, evaluation
                ).success_rates
                curves.setdefault(arm, {}).setdefault(str(seed), {})[budget] = rates
                print(
                    f"{arm} seed {seed} @ {budget}: mean {100 * np.mean(list(rates.values())):.1f}",
                    flush=True,
                )
    write(args, curves, time.perf_counter() - start)


def rule(args: argparse.Namespace, curves: dict) -> dict[str, dict]:
    """Per task: each seed's mean success over the budgets (points) and whether the rule keeps it."""
    out = {}
    for task in args.candidates:
        per_seed = [100 * np.mean([curves["sft"][s][b][task] for b in args.budgets]) for s in curves["sft"]]
        mean = float(np.mean(per_seed))
        keep = args.low <= mean <= args.high and max(abs(x - mean) for x in per_seed) <= args.spread
        out[task] = {"per_seed": per_seed, "mean": mean, "chosen": bool(keep)}
    return out


def write(args: argparse.Namespace, curves: dict, seconds: float) -> None:
    args.out.parent.mkdir(parents=True, exist_ok=True)
    verdict = rule(args, curves)
    doc = {
        "args": {k: str(v) for k, v in vars(args).items()},
        "curves": curves,
        "rule": verdict,
        "chosen": [t for t, v in verdict.items() if v["chosen"]],
        "seconds": round(seconds),
    }
    args.out.with_suffix(".json").write_text(json.dumps(doc, indent=1) + "\n")
    arms = list(curves)
    head = (
        "| task | " + " | ".join(f"{a} @ {b}" for a in arms for b in args.budgets) + " | SFT mean | chosen |"
    )
    lines = [
        "# Calibration: SFT learning curves per task (validation goals)",
        "",
        f"θ_pt: {args.pretrain_steps} steps on {len(PRETRAIN)} tasks; fine-tuned on all "
        f"{len(args.candidates)} candidates together, {args.episodes} demos each, seeds {args.seeds}; "
        f"{args.goals} validation goals "
        f"per task; observation transform `{args.transform}`. Cells: success (%) averaged over seeds.",
        "",
        f"Rule: SFT's mean success over budgets {args.budgets} within [{args.low:g}, {args.high:g}] and no "
        f"seed more than {args.spread:g} points from the mean. Wall time {seconds / 60:.1f} min.",
        "",
        head,
        "|" + "---|" * (3 + len(arms) * len(args.budgets)),
    ]
    for task, v in verdict.items():
        cells = [
            f"{100 * np.mean([curves[a][s][b][task] for s in curves[a]]):.0f}"
            for a in arms
            for b in args.budgets
        ]
        lines.append(
            f"| {task} | " + " | ".join(cells) + f" | {v['mean']:.0f} | {'yes' if v['chosen'] else ''} |"
        )
    lines += ["", f"Chosen: {', '.join(doc['chosen']) or 'none'}"]
    args.out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
