"""Benchmark (b): training samples/s of `trainer.train` against a plain PyTorch loop.

Same model (same initial weights), same batches (same generator seed and gather), same AdamW,
schedule and clipping; the plain loop has none of the trainer's bookkeeping (NaN checks, loss
curve, checkpoints, resume state, validation). Runs alternate (ours, plain, plain, ours, ...) in
one process so machine load affects both alike. Both timings are whole calls, set-up included.
Target: our overhead <= 10%.

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

from capvector_core import tokenizer
from capvector_core.policy import PolicyConfig, VLAPolicy
from capvector_core.trainer import (
    SampleTable,
    TrainConfig,
    _instructions,
    _param_groups,
    _stats,
    lr_at,
    train,
)

ROOT = Path(__file__).resolve().parent
RESULTS = ROOT / "results"


def plain_loop(policy: VLAPolicy, dataset, config: TrainConfig) -> None:
    """The minimal loop a researcher would write for the same training."""
    tensors = dataset.tensors
    cfg = policy.config
    policy.normalizer.set_stats(_stats(tensors))
    chunk = SampleTable(tensors, cfg.chunk_size, None).chunk
    tokens = tokenizer.encode_batch(_instructions(dataset.meta), cfg.vocab_size, cfg.max_instruction_tokens)
    params = list(policy.parameters())
    optimizer = torch.optim.AdamW(_param_groups(params, config.weight_decay), lr=config.lr)
    generator = torch.Generator().manual_seed(config.seed)
    n = tensors["action"].shape[0]
    policy.train()
    for step in range(config.steps):
        for group in optimizer.param_groups:
            group["lr"] = lr_at(step, config)
        idx = torch.randint(n, (config.batch_size,), generator=generator)
        batch = {
            "tokens": tokens[tensors["task"][idx]],
            "state": tensors["state"][idx],
            "proprio": tensors["proprio"][idx],
        }
        loss = policy.action_loss(policy(batch)["actions"], tensors["action"][chunk[idx]])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, config.grad_clip)
        optimizer.step()


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
    policy_config = PolicyConfig(d_model=args.d_model, n_layers=4, n_heads=4, chunk_size=8)
    config = TrainConfig(
        steps=args.steps,
        batch_size=args.batch_size,
        warmup_steps=args.steps // 10,
        checkpoint_every=args.checkpoint_every,
        log_every=10,
        device="cpu",
        num_threads=args.threads,
    )
    torch.manual_seed(0)
    initial = VLAPolicy(policy_config).state_dict()
    times: dict[str, list[float]] = {"ours": [], "plain": []}
    work = Path(tempfile.mkdtemp(prefix="bench-train-"))
    try:
        # untimed warm-up of both: the first call in a process pays one-time lazy imports inside torch
        warm = config.model_copy(update={"steps": 5, "warmup_steps": 1})
        train(VLAPolicy(policy_config), dataset, warm, work / "warmup", progress=False)
        plain_loop(VLAPolicy(policy_config), dataset, warm)
        for r in range(args.rounds):
            order = ["ours", "plain"] if r % 2 == 0 else ["plain", "ours"]
            for which in order:
                policy = VLAPolicy(policy_config)
                policy.load_state_dict(initial)
                start = time.perf_counter()
                if which == "ours":
                    train(policy, dataset, config, work / f"run{r}", progress=False)
                else:
                    plain_loop(policy, dataset, config)
                times[which].append(time.perf_counter() - start)
                print(f"round {r} {which}: {args.steps * args.batch_size / times[which][-1]:.0f} samples/s")
    finally:
        shutil.rmtree(work, ignore_errors=True)

    samples = args.steps * args.batch_size
    ours = samples / (sum(times["ours"]) / args.rounds)
    plain = samples / (sum(times["plain"]) / args.rounds)
    overhead = plain / ours - 1.0
    entry = {
        "policy": policy_config.model_dump(),
        "steps_per_run": args.steps,
        "rounds": args.rounds,
        "batch_size": args.batch_size,
        "checkpoint_every": args.checkpoint_every,
        "dataset_steps": len(dataset),
        "ours_samples_per_s": round(ours, 1),
        "plain_samples_per_s": round(plain, 1),
        "ours_seconds": [round(t, 2) for t in times["ours"]],
        "plain_seconds": [round(t, 2) for t in times["plain"]],
        "overhead": round(overhead, 4),
        "target_overhead": 0.10,
        "params": sum(p.numel() for p in VLAPolicy(policy_config).parameters()),
        "torch_threads": args.threads,
    }
    print(json.dumps(entry, indent=1))
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "train.json").write_text(json.dumps(entry, indent=1) + "\n")
    (RESULTS / "train.md").write_text(
        "# Training throughput (benchmark b)\n\n"
        "`trainer.train` vs a plain PyTorch loop: same model and initial weights, same batches, AdamW,\n"
        "schedule and clipping; alternating runs in one process; whole calls timed (set-up, checkpoints\n"
        f"every {args.checkpoint_every} steps and the final save included). CPU, "
        f"{args.threads} torch thread(s);\n"
        "the machine is shared with other work, so absolute numbers vary between runs;\n"
        "the ratio is the measurement.\n\n"
        "| model | batch | steps x rounds | ours samples/s | plain samples/s | overhead | target |\n"
        "|---|---|---|---|---|---|---|\n"
        f"| state d={args.d_model}, 4 layers, K=8, T={policy_config.n_tokens} | {args.batch_size} | "
        f"{args.steps} x {args.rounds} | {ours:.0f} | {plain:.0f} | {overhead:+.1%} | <= +10% |\n"
    )


if __name__ == "__main__":
    main()
