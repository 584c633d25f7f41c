"""Pilot: where does an auxiliary objective help? Held-out action loss of SFT vs SFT + objective.

Cheap (training and held-out demonstrations only, no rollouts), so it can scan observation transforms,
objectives and weights before a study spends rollouts on one: for each transform frequency a θ_pt is
pretrained, then each arm is fine-tuned on the downstream tasks over `--seeds` and its action loss is
measured on held-out demonstrations of those tasks (seeds after the training demos'). No test or
validation goal is used. Writes JSON and Markdown to --out.

    python scripts/pilot_aux.py --tasks door-close-v3 faucet-open-v3 --frequencies 0.3 1 3
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time
from pathlib import Path

import numpy as np
import torch

from capvector.core.policies.base import build_policy, load_policy
from capvector.core.simulation.demos import UNIT_SEEDS, DemoConfig, DemoDataset, collect_demos
from capvector.core.simulation.obs_transforms import ObsTransformConfig
from capvector.core.training.held_out_loss import held_out_action_loss
from capvector.core.training.trainer import AuxConfig, TrainConfig, train
from capvector.flows.calibration.config import load_calibration

PRETRAIN = load_calibration("calibrate-control").splits.pretrain
"""θ_pt's tasks: the calibration's (and the control studies')."""


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
    ap.add_argument("--out", type=Path, default=Path("capvector_home/calibration/pilot-aux"))
    ap.add_argument("--tasks", nargs="+", required=True)
    ap.add_argument("--episodes", type=int, default=5)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--frequencies", type=float, nargs="+", default=[1.0], help="0: identity (no transform)")
    ap.add_argument("--aliased", nargs="+", default=["goal"], help="positions the distractors encode")
    ap.add_argument("--hide-aliased", action="store_true", help="leave them out of the random features")
    ap.add_argument("--arms", nargs="+", default=["spatial:0.5", "spatial:2", "dynamics:0.5"])
    args = ap.parse_args()
    torch.set_num_threads(1)
    start = time.perf_counter()
    pre = cached_demos(DemoConfig(tasks=PRETRAIN, episodes_per_task=10, horizon=500, workers=2), args.work)
    train_demos = DemoConfig(tasks=args.tasks, episodes_per_task=args.episodes, horizon=500, workers=2)
    down = cached_demos(train_demos, args.work)
    held = cached_demos(
        train_demos.model_copy(update={"seed_offset": train_demos.n_units * UNIT_SEEDS}), args.work
    )
    results: dict[str, dict[str, list[float]]] = {}
    for freq in args.frequencies:
        transform = ObsTransformConfig(
            kind="random_features", frequency=freq, aliased=args.aliased, hide_aliased=args.hide_aliased
        )
        transform = transform if freq else ObsTransformConfig()
        variant = f"f{freq:g}" + (f"-hide-{'-'.join(args.aliased)}" if args.hide_aliased and freq else "")
        policy_config = {"obs_mode": "state", "d_model": 64, "n_layers": 2, "n_heads": 4, "chunk_size": 8}
        config = {**policy_config, "obs_transform": transform.model_dump()}
        pt = pretrain_policy(config, pre, 1500, args.work / f"pretrain-{variant}")
        for arm in ["sft", *args.arms]:
            name, _, weight = arm.partition(":")
            aux = None if name == "sft" else AuxConfig(name=name, weight=float(weight))
            for seed in args.seeds:
                config = TrainConfig(
                    steps=args.steps,
                    batch_size=64,
                    lr=1e-3,
                    warmup_steps=20,
                    seed=seed,
                    checkpoint_every=args.steps,
                    num_threads=1,
                    device="cpu",
                    aux=aux,
                )
                run = args.work / f"pilot-{variant}-{'-'.join(args.tasks)[:40]}-{arm}-{seed}"
                path = train(load_policy(pt, device="cpu"), down, config, run).weights_path
                loss = held_out_action_loss(path, held, 256, 0)
                results.setdefault(variant, {}).setdefault(arm, []).append(loss)
                print(f"{variant} {arm} seed {seed}: held-out action loss {loss:.4f}", flush=True)
    write(args, results, time.perf_counter() - start)


def write(args: argparse.Namespace, results: dict, seconds: float) -> None:
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(
        json.dumps({"args": vars(args), "loss": results}, default=str) + "\n"
    )
    lines = [
        "# Pilot: held-out action loss, SFT vs SFT + auxiliary objective",
        "",
        f"Tasks {', '.join(args.tasks)}; {args.episodes} demos each; {args.steps} steps; seeds {args.seeds}; "
        f"wall {seconds / 60:.1f} min. Loss on held-out demonstrations (lower is better); Δ = arm − SFT per "
        "seed (paired), and how many seeds it is below 0.",
        "",
        "| transform | arm | loss (mean) | Δ vs SFT (mean) | seeds better |",
        "|---|---|---|---|---|",
    ]
    for freq, arms in results.items():
        sft = np.array(arms["sft"])
        for arm, values in arms.items():
            delta = np.array(values) - sft
            lines.append(
                f"| {freq} | {arm} | {np.mean(values):.4f} | {delta.mean():+.4f} | "
                f"{int((delta < 0).sum())}/{len(delta)} |"
            )
    args.out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
