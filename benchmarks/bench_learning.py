"""Benchmark (d): does the stack learn? A multi-task policy on 8 Meta-World v3 tasks from 25 expert demos
each, evaluated on 20 held-out goal variations per task (evaluation seeds, disjoint from demo seeds).

Budgets are arguments: the state run is the issue's target (>= 80% mean success within 15 min of
training); the pixels run (64x64) uses whatever budget is passed. Demos are cached under
benchmarks/_work/ by their config, so reruns only train and evaluate.

    python benchmarks/bench_learning.py --mode state --steps 6000
    python benchmarks/bench_learning.py --mode state --steps 3000 --policy flow --tag flow
    python benchmarks/bench_learning.py --mode pixels --steps 3000 --max-train-minutes 30
"""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
import shutil
import time
from pathlib import Path

import torch

from capvector.core.evaluation.rollouts import EvalConfig, evaluate
from capvector.core.policies.base import build_policy, policy_types
from capvector.core.simulation.demos import DemoConfig, DemoDataset, collect_demos
from capvector.core.training.trainer import TrainConfig, train

TASKS = [
    "reach-v3",
    "push-v3",
    "drawer-open-v3",
    "drawer-close-v3",
    "button-press-topdown-v3",
    "window-open-v3",
    "window-close-v3",
    "door-open-v3",
]
ROOT = Path(__file__).resolve().parent
WORK = ROOT / "_work" / "learning"  # --work-dir overrides (benchmarks/_work is shared with other jobs)
RESULTS = ROOT / "results"


def demos(mode: str, episodes: int, image_size: int, work: Path = WORK) -> tuple[DemoDataset, float]:
    config = DemoConfig(tasks=TASKS, episodes_per_task=episodes, obs_mode=mode, image_size=image_size)
    key = hashlib.sha256(config.model_dump_json(exclude={"workers"}).encode()).hexdigest()[:12]
    path = work / f"demos-{mode}-{key}"
    if path.exists():
        return DemoDataset.load(path), 0.0
    start = time.perf_counter()
    dataset = collect_demos(config)
    seconds = time.perf_counter() - start
    dataset.save(path)
    return dataset, seconds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mode", choices=["state", "pixels"], default="state")
    ap.add_argument("--policy", default="l1_chunk", help=f"policy type ({', '.join(policy_types())})")
    ap.add_argument("--episodes", type=int, default=25, help="demos per task")
    ap.add_argument("--eval-episodes", type=int, default=20, help="held-out goal variations per task")
    ap.add_argument("--steps", type=int, default=6000)
    ap.add_argument("--batch-size", type=int, default=64)
    ap.add_argument("--lr", type=float, default=5e-4)
    ap.add_argument("--d-model", type=int, default=128)
    ap.add_argument("--layers", type=int, default=4)
    ap.add_argument("--chunk", type=int, default=8)
    ap.add_argument("--execute", type=int, default=4, help="actions executed per policy call")
    ap.add_argument("--image-size", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--threads", type=int, default=1, help="torch threads (1 copes best with other jobs on the cores)"
    )
    ap.add_argument("--work-dir", type=Path, default=WORK, help="demo cache and run directories")
    ap.add_argument("--tag", default="", help="suffix for the run directory and result entry")
    ap.add_argument("--fresh", action="store_true", help="delete the run directory first (no resume)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    dataset, demo_seconds = demos(args.mode, args.episodes, args.image_size, args.work_dir)
    print(
        f"demos: {len(dataset)} steps, {dataset.meta.n_episodes} episodes, failures {dataset.meta.failures}"
    )
    torch.manual_seed(args.seed)
    policy = build_policy(
        {
            "type": args.policy,
            "obs_mode": args.mode,
            "d_model": args.d_model,
            "n_layers": args.layers,
            "n_heads": 4,
            "chunk_size": args.chunk,
            "image_size": args.image_size,
        },
        device="auto",
    )
    policy_config = policy.config
    train_config = TrainConfig(
        steps=args.steps,
        batch_size=args.batch_size,
        lr=args.lr,
        warmup_steps=min(200, args.steps // 10),
        seed=args.seed,
        checkpoint_every=max(500, args.steps // 4),
        log_every=50,
        device="auto",
        num_threads=args.threads,
    )
    name = f"{args.mode}{'-' + args.tag if args.tag else ''}"
    run_dir = args.work_dir / f"run-{name}"
    if args.fresh:
        shutil.rmtree(run_dir, ignore_errors=True)
    result = train(policy, dataset, train_config, run_dir)
    train_seconds = result.train_seconds
    print(f"trained {args.steps} steps in {train_seconds:.0f}s, final loss {result.final_loss:.4f}")

    eval_config = EvalConfig(
        tasks=TASKS,
        episodes_per_task=args.eval_episodes,
        obs_mode=args.mode,
        image_size=args.image_size,
        execute_steps=args.execute,
    )
    evaluation = evaluate(policy.predict_action_chunk, eval_config)
    print(f"mean success {evaluation.mean_success:.3f}: {evaluation.success_rates}")

    entry = {
        "mode": args.mode,
        "policy_type": args.policy,
        "tag": args.tag,
        "tasks": TASKS,
        "demos_per_task": args.episodes,
        "demo_steps": len(dataset),
        "demo_seconds": round(demo_seconds, 1),
        "policy": policy_config.model_dump(mode="json"),
        "train": train_config.model_dump(),
        "params": sum(p.numel() for p in policy.parameters()),
        "train_seconds": round(train_seconds, 1),
        "train_samples_per_s": round(args.steps * args.batch_size / train_seconds, 1),
        "final_loss": round(result.final_loss, 5),
        "execute_steps": args.execute,
        "eval_episodes_per_task": args.eval_episodes,
        "eval_seconds": round(evaluation.wall_time_s, 1),
        "success_rates": evaluation.success_rates,
        "mean_success": evaluation.mean_success,
        "fingerprint": evaluation.fingerprint,
        "machine": f"{platform.processor() or platform.machine()}, torch threads {args.threads}",
    }
    write_results(name, entry)


def write_results(name: str, entry: dict) -> None:
    """Merge this run into results/learning.json (one entry per mode/tag) and regenerate the table."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    path = RESULTS / "learning.json"
    runs = json.loads(path.read_text()) if path.exists() else {}
    runs[name] = entry
    path.write_text(json.dumps(runs, indent=1, sort_keys=True) + "\n")
    lines = [
        "# Learning check (benchmark d)",
        "",
        "Multi-task policy on 8 Meta-World v3 tasks, 25 expert demos each; success over held-out goal",
        "variations (evaluation seeds). Target: state mode >= 80% mean success with <= 15 min training.",
        "Generated by `benchmarks/bench_learning.py` (one row per run; `_notes` in learning.json is kept).",
        "",
    ]
    header = "| run | policy | train steps | train min | K / executed | mean success | " + " | ".join(
        t.removesuffix("-v3") for t in TASKS
    )
    lines += [header + " |", "|" + "---|" * (6 + len(TASKS))]
    for run_name, e in sorted(runs.items()):
        if run_name.startswith("_"):
            continue
        rates = " | ".join(f"{e['success_rates'].get(t, float('nan')):.2f}" for t in TASKS)
        lines.append(
            f"| {run_name} | {e.get('policy_type', 'l1_chunk')} | {e['train']['steps']} | "
            f"{e['train_seconds'] / 60:.1f} | "
            f"{e['policy']['chunk_size']} / {e['execute_steps']} | **{e['mean_success']:.3f}** | {rates} |"
        )
    if runs.get("_notes"):
        lines += ["", "## Notes", ""] + [f"- {note}" for note in runs["_notes"]]
    (RESULTS / "learning.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
