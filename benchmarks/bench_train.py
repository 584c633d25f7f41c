"""Benchmark (b): training samples/s of `trainer.train` against a plain PyTorch loop, per policy type.

Same model (same initial weights), same batches (same generator seed, the policy's own batcher), same
AdamW, schedule and clipping; the plain loop has none of the trainer's bookkeeping (NaN checks, loss
curve, checkpoints, resume state, validation). Runs alternate (ours, plain, plain, ours, ...) in
one process so machine load affects both alike. Both timings are whole calls, set-up included.
Target: our overhead <= 10% for every built-in backbone.

    python benchmarks/bench_train.py --steps 300 --rounds 3
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import torch

from capvector.core.policies.base import Policy, build_policy
from capvector.core.training.trainer import TrainConfig, _param_groups, lr_at, train

ROOT = Path(__file__).resolve().parent
RESULTS = ROOT / "results"
TYPES = ["l1_chunk", "flow"]


def plain_loop(
    policy: Policy, dataset, config: TrainConfig, device: torch.device = torch.device("cpu")
) -> None:
    """The minimal loop a researcher would write for the same training, on `device`. The policy draws
    its loss's randomness from a generator on `device`, as in `train` (without one, flow matching draws
    its times on the CPU and copies them over each step: a cost that is not the trainer's)."""
    if config.num_threads:
        torch.set_num_threads(config.num_threads)
    policy.fit_normalizer(dataset.tensors)
    n, make_batch = policy.make_batcher(dataset, device)
    policy.to(device).train()
    policy.set_generator(torch.Generator(device=device).manual_seed(config.seed))
    params = list(policy.parameters())
    optimizer = torch.optim.AdamW(_param_groups(params, config.weight_decay), lr=config.lr)
    generator = torch.Generator().manual_seed(config.seed)
    for step in range(config.steps):
        for group in optimizer.param_groups:
            group["lr"] = lr_at(step, config)
        loss = policy.compute_loss(
            make_batch(torch.randint(n, (config.batch_size,), generator=generator))
        ).loss
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, config.grad_clip)
        optimizer.step()


def measure(policy_type: str, dataset, args, config: TrainConfig, work: Path) -> dict:
    spec = {"type": policy_type, "d_model": args.d_model, "n_layers": 4, "n_heads": 4, "chunk_size": 8}
    torch.manual_seed(0)
    initial = build_policy(spec, "cpu").state_dict()
    times: dict[str, list[float]] = {"ours": [], "plain": []}
    # untimed warm-up of both: the first call in a process pays one-time lazy imports inside torch
    warm = config.model_copy(update={"steps": 5, "warmup_steps": 1})
    train(build_policy(spec, "cpu"), dataset, warm, work / f"warmup-{policy_type}", progress=None)
    plain_loop(build_policy(spec, "cpu"), dataset, warm)
    for r in range(args.rounds):
        order = ["ours", "plain"] if r % 2 == 0 else ["plain", "ours"]
        for which in order:
            policy = build_policy(spec, "cpu")
            policy.load_state_dict(initial)
            start = time.perf_counter()
            if which == "ours":
                train(policy, dataset, config, work / f"run-{policy_type}-{r}", progress=None)
            else:
                plain_loop(policy, dataset, config)
            times[which].append(time.perf_counter() - start)
            rate = args.steps * args.batch_size / times[which][-1]
            print(f"{policy_type} round {r} {which}: {rate:.0f} samples/s")
    samples = args.steps * args.batch_size
    ours = samples / (sum(times["ours"]) / args.rounds)
    plain = samples / (sum(times["plain"]) / args.rounds)
    # each round's two runs are adjacent in time: their ratio cancels slow drifts in machine load
    paired = sorted(o / p - 1.0 for o, p in zip(times["ours"], times["plain"], strict=True))
    return {
        "policy": build_policy(spec, "cpu").config.model_dump(mode="json"),
        "ours_samples_per_s": round(ours, 1),
        "plain_samples_per_s": round(plain, 1),
        "ours_seconds": [round(t, 2) for t in times["ours"]],
        "plain_seconds": [round(t, 2) for t in times["plain"]],
        "overhead": round(paired[len(paired) // 2], 4),
        "overhead_of_means": round(plain / ours - 1.0, 4),
        "overhead_per_round": [round(x, 4) for x in paired],
        "params": sum(p.numel() for p in build_policy(spec, "cpu").parameters()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--batch-size", type=int, default=64)
    ap.add_argument("--d-model", type=int, default=128)
    ap.add_argument("--checkpoint-every", type=int, default=100)
    ap.add_argument("--work-dir", type=Path, default=None, help="demo cache (default: bench_learning's)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (1 copes best with other jobs)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    from bench_learning import WORK, demos  # the learning check's cached 8-task state demos

    dataset, _ = demos("state", 25, 64, args.work_dir or WORK)
    config = TrainConfig(
        steps=args.steps,
        batch_size=args.batch_size,
        warmup_steps=args.steps // 10,
        checkpoint_every=args.checkpoint_every,
        log_every=10,
        device="cpu",
        num_threads=args.threads,
    )
    work = Path(tempfile.mkdtemp(prefix="bench-train-"))
    try:
        per_type = {t: measure(t, dataset, args, config, work) for t in TYPES}
    finally:
        shutil.rmtree(work, ignore_errors=True)
    entry = {
        "steps_per_run": args.steps,
        "rounds": args.rounds,
        "batch_size": args.batch_size,
        "checkpoint_every": args.checkpoint_every,
        "dataset_steps": len(dataset),
        "target_overhead": 0.10,
        "torch_threads": args.threads,
        "policies": per_type,
    }
    print(json.dumps(entry, indent=1))
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "train.json").write_text(json.dumps(entry, indent=1) + "\n")
    rows = "".join(
        f"| {t} | state d={args.d_model}, 4 layers, K=8 | {e['params']:,} | {args.batch_size} | "
        f"{args.steps} x {args.rounds} | {e['ours_samples_per_s']:.0f} | {e['plain_samples_per_s']:.0f} | "
        f"{e['overhead']:+.1%} | <= +10% |\n"
        for t, e in per_type.items()
    )
    (RESULTS / "train.md").write_text(
        "# Training throughput (benchmark b)\n\n"
        "`trainer.train` vs a plain PyTorch loop, per policy type: same model and initial weights, same\n"
        "batches (the policy's batcher), AdamW, schedule and clipping; alternating runs in one process;\n"
        f"whole calls timed (set-up, checkpoints every {args.checkpoint_every} steps and the final save\n"
        f"included). CPU, {args.threads} torch thread(s); the machine is shared with other work, so\n"
        "absolute numbers vary between runs; the ratio is the measurement: overhead is the median over\n"
        "rounds of (our time / plain time − 1), each round's two runs adjacent in time.\n\n"
        "| policy | model | params | batch | steps x rounds | ours samples/s | plain samples/s | overhead "
        "| target |\n"
        "|---|---|---|---|---|---|---|---|---|\n" + rows
    )


if __name__ == "__main__":
    main()
