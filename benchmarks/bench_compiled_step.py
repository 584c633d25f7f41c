"""Is a compiled training step worth it on the CPU? (issue 39: use it if ≥ 1.2× faster, results equal
within float tolerance.)

The same l1_chunk policy (state, d_model 128 × 4 layers, batch 64) and the same batches, one AdamW step
each: eager `compute_loss` against `torch.compile(policy.compute_loss)` (inductor, which fuses the
elementwise work). Times are medians of timed steps after warm-up (compilation excluded and reported
apart); the loss after each of the first steps and the weights after them are compared between the two.

    python benchmarks/bench_compiled_step.py --steps 60 --threads 1
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch
from bench_train_cuda import make_dataset  # run as a script: benchmarks/ is on sys.path

from capvector.core.policies.base import build_policy
from capvector.core.simulation.demos import DemoDataset

RESULTS = Path(__file__).resolve().parent / "results"


def run(compiled: bool, steps: int, warmup: int, dataset: DemoDataset, batches: list) -> dict:
    """Train `steps` steps from the same weights; per-step seconds after `warmup`, losses, final weights."""
    torch.manual_seed(0)
    policy = build_policy({"type": "l1_chunk", "obs_mode": "state", "d_model": 128, "n_layers": 4}, "cpu")
    policy.fit_normalizer(dataset.tensors)
    optimizer = torch.optim.AdamW(policy.parameters(), lr=1e-3)
    loss_of = torch.compile(policy.compute_loss) if compiled else policy.compute_loss
    policy.train()
    times, losses, first = [], [], None
    for step in range(steps):
        batch = batches[step % len(batches)]
        start = time.perf_counter()
        loss = torch.stack(list(loss_of(batch).terms.values())).sum()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        took = time.perf_counter() - start
        first = took if first is None else first
        losses.append(loss.item())
        if step >= warmup:
            times.append(took)
    weights = torch.cat([p.detach().flatten() for p in policy.parameters()])
    return {"median_s": statistics.median(times), "first_step_s": first, "losses": losses, "weights": weights}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--warmup", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--results", type=Path, default=RESULTS)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    dataset = make_dataset()
    probe = build_policy({"type": "l1_chunk", "obs_mode": "state", "d_model": 128, "n_layers": 4}, "cpu")
    n, make_batch = probe.make_batcher(dataset, torch.device("cpu"))
    g = torch.Generator().manual_seed(1)
    batches = [make_batch(torch.randint(n, (64,), generator=g)) for _ in range(8)]
    eager = run(False, args.steps, args.warmup, dataset, batches)
    print(f"eager: {eager['median_s'] * 1e3:.1f} ms/step", flush=True)
    compiled = run(True, args.steps, args.warmup, dataset, batches)
    print(f"compiled: {compiled['median_s'] * 1e3:.1f} ms/step (first step {compiled['first_step_s']:.1f} s)")
    loss_diff = max(abs(a - b) for a, b in zip(eager["losses"], compiled["losses"], strict=True))
    weight_diff = float((eager["weights"] - compiled["weights"]).abs().max())
    result = {
        "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "torch": torch.__version__,
        "threads": args.threads,
        "steps": args.steps,
        "eager_ms": eager["median_s"] * 1e3,
        "compiled_ms": compiled["median_s"] * 1e3,
        "speedup": eager["median_s"] / compiled["median_s"],
        "compile_first_step_s": compiled["first_step_s"],
        "max_loss_diff": loss_diff,
        "max_weight_diff": weight_diff,
    }
    print(json.dumps(result, indent=1))
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "compiled_step.json").write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
