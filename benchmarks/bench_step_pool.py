"""Benchmark: a study-shaped graph of steps on `StepPool` vs Prefect's stock `ProcessPoolTaskRunner`.

The shape is a study's tuning grid: each value's training step is followed by two steps that read its
checkpoint (validation, held-out loss), submitted in that order, on 2 workers. Steps sleep instead of
training, so the measurement is the scheduling alone: makespan from the first submit to the last
result, inside one flow per runner (the flow's start-up excluded), runners alternating over rounds.
With the stock pool the two waiting steps of the first value hold both input-resolving threads, so the
second value's training waits for the first's to end (capvector.flows.runtime.step_pool).

    python benchmarks/bench_step_pool.py [--values 4] [--train-s 3] [--read-s 0.3] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import capvector.flows  # noqa: F401  (first: its __init__ sets Prefect's environment, no telemetry in the timings)

# isort: split
from prefect import flow, task
from prefect.task_runners import ProcessPoolTaskRunner

from capvector.flows.runtime.step_pool import StepPool

RESULTS = Path(__file__).resolve().parent / "results"
RUNNERS = {"stock": ProcessPoolTaskRunner, "step_pool": StepPool}


@task
def step(seconds: float, *inputs: float) -> float:
    time.sleep(seconds)
    return seconds


@flow(persist_result=False)
def tuning_grid(values: int, train_s: float, read_s: float) -> float:
    start = time.perf_counter()
    futures = []
    for _ in range(values):
        trained = step.submit(train_s)
        futures += [trained, step.submit(read_s, trained), step.submit(read_s, trained)]
    for future in futures:
        future.result()
    return time.perf_counter() - start


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--values", type=int, default=4)
    ap.add_argument("--train-s", type=float, default=3.0)
    ap.add_argument("--read-s", type=float, default=0.3)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    seconds: dict[str, list[float]] = {name: [] for name in RUNNERS}
    for r in range(args.rounds):
        for name in RUNNERS if r % 2 == 0 else list(RUNNERS)[::-1]:
            runner = RUNNERS[name](max_workers=2)
            seconds[name].append(
                tuning_grid.with_options(task_runner=runner)(args.values, args.train_s, args.read_s)
            )
        print(f"round {r}: " + ", ".join(f"{k} {v[-1]:.2f} s" for k, v in seconds.items()))
    median = {k: statistics.median(v) for k, v in seconds.items()}
    floor = args.values * args.train_s / 2 + args.read_s  # 2 workers, training steps in pairs
    entry = {
        "values": args.values,
        "train_s": args.train_s,
        "read_s": args.read_s,
        "rounds": args.rounds,
        "workers": 2,
        "seconds": {k: [round(x, 2) for x in v] for k, v in seconds.items()},
        "median_s": {k: round(v, 2) for k, v in median.items()},
        "ratio_step_pool_to_stock": round(median["step_pool"] / median["stock"], 3),
        "two_worker_floor_s": round(floor, 2),
    }
    print(json.dumps(entry, indent=1))
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "step_pool.json").write_text(json.dumps(entry, indent=1) + "\n")
    (RESULTS / "step_pool.md").write_text(
        "# Scheduling: StepPool vs Prefect's stock process pool\n\n"
        f"`benchmarks/bench_step_pool.py --values {args.values} --train-s {args.train_s} "
        f"--read-s {args.read_s} --rounds {args.rounds}`: a tuning grid of {args.values} training steps "
        f"({args.train_s} s each), each followed by two {args.read_s} s steps that read its result, "
        "submitted in that order on 2 workers; steps sleep, so this times the scheduling alone. Makespan "
        "from the first submit to the last result, median over rounds, runners alternating.\n\n"
        "| runner | makespan (s) | rounds (s) |\n|---|---|---|\n"
        + "".join(
            f"| {name} | {median[name]:.2f} | {', '.join(f'{x:.2f}' for x in seconds[name])} |\n"
            for name in RUNNERS
        )
        + f"\nStepPool / stock: **{entry['ratio_step_pool_to_stock']:.2f}×**. The 2-worker floor "
        f"(training steps in pairs, then one read) is {floor:.2f} s; both makespans also hold the "
        "pool's start (spawned workers importing Prefect) and Prefect's per-step work in a worker "
        "(task-run records in its API), equal for both runners. On the stock pool the training steps "
        "run one at a time.\n"
    )


if __name__ == "__main__":
    main()
