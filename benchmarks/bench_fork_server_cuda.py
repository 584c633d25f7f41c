"""CUDA in step workers forked from the step pool's fork server (flows/runtime/fork_server.py), on a lent GPU.

The fork server imports torch (and torch._dynamo, Meta-World) before it forks any worker. A process forked
after CUDA was initialised in its parent cannot use the GPU; the server never initialises CUDA, so its
workers can. This check trains the same policy (l1_chunk, synthetic state demos, bench_train_cuda's) on the
device in two workers forked from the server at once, and in one spawned worker (Prefect's start method),
and compares their final weights: bitwise equal, as two straight runs of this model on an H100 were
(benchmarks/results/train_cuda.md). Also recorded: whether CUDA was initialised in each worker before its
training (it must not be), and each worker's seconds from submit to result.

    PYTHONPATH=. python benchmarks/bench_fork_server_cuda.py [--steps 200]
    PYTHONPATH=. python benchmarks/bench_fork_server_cuda.py --device cpu --quick   (a dry run)

On a lent GPU machine without EGL, run it with MUJOCO_GL=disable (nothing here renders).

Prefect need not be installed: the server then skips the preloaded modules that import it, as it skips
any module that fails to import.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import multiprocessing
import tempfile
import time
from pathlib import Path

import torch
from bench_train_cuda import (  # run as a script: benchmarks/ is on sys.path
    add_device_options,
    cpu_state,
    difference,
    entry_of,
    make_dataset,
    say,
    write_results,
)

from capvector.core.policies.base import build_policy
from capvector.core.training.device import run_environment
from capvector.core.training.trainer import TrainConfig, train
from capvector.flows.runtime.fork_server import preload_modules, preloaded_fork_server

STEM = "fork_server_cuda"


def train_in_worker(spec: dict, steps: int, device: str, batch_size: int, threads: int) -> dict:
    """In a pool worker: CUDA's state as the worker starts, then a whole training run from seed-0 weights."""
    started_initialised = torch.cuda.is_initialized()
    torch.manual_seed(0)
    policy = build_policy(spec, "cpu")
    config = TrainConfig(
        steps=steps,
        batch_size=batch_size,
        warmup_steps=steps // 10,
        checkpoint_every=steps,
        log_every=10,
        device=device,
        num_threads=threads,
    )
    with tempfile.TemporaryDirectory() as run_dir:
        result = train(policy, make_dataset(), config, Path(run_dir))
    return {
        "cuda_initialised_at_start": started_initialised,
        "steps_per_s": result.steps_per_s,
        "weights": cpu_state(policy),
    }


def run_pool(context, workers: int, args, spec: dict) -> list[dict]:
    """`workers` trainings submitted at once to a fresh pool on `context`; seconds from submit to result."""
    with concurrent.futures.ProcessPoolExecutor(workers, mp_context=context) as pool:
        started = time.perf_counter()
        futures = [
            pool.submit(train_in_worker, spec, args.steps, args.device, args.batch_size, args.device_threads)
            for _ in range(workers)
        ]
        results = []
        for future in futures:
            out = future.result()
            out["seconds_to_result"] = time.perf_counter() - started
            results.append(out)
    return results


def markdown(entry: dict) -> str:
    forked, spawned = entry["forked"], entry["spawned"]
    rows = [
        f"| forked {i + 1} | {w['cuda_initialised_at_start']} | {w['steps_per_s']:.1f} | "
        f"{w['seconds_to_result']:.1f} |"
        for i, w in enumerate(forked)
    ] + [
        f"| spawned | {spawned['cuda_initialised_at_start']} | {spawned['steps_per_s']:.1f} | "
        f"{spawned['seconds_to_result']:.1f} |"
    ]

    def same(diff: dict) -> str:
        return "bitwise equal" if diff["bitwise_equal"] else f"max diff {diff['max_abs_diff']:.3g}"

    env = entry["environment"]
    return "\n".join(
        [
            "# CUDA in workers forked from the step pool's fork server",
            "",
            f"{entry['date']}: {env.get('device_name', entry['args']['device'])}, torch {env.get('torch')}. "
            f"l1_chunk d_model {entry['args']['d_model']}, {entry['args']['steps']} steps, batch "
            f"{entry['args']['batch_size']}, synthetic state demos. `benchmarks/bench_fork_server_cuda.py`.",
            "",
            "| worker | CUDA initialised at start | steps/s | s from submit to result |",
            "|---|---|---|---|",
            *rows,
            "",
            f"Final weights: forked 1 vs forked 2 {same(entry['forked_vs_forked'])}; forked 1 vs spawned "
            f"{same(entry['forked_vs_spawned'])}. Preloaded in the server: {', '.join(entry['preloaded'])}.",
            "",
        ]
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_device_options(ap, STEM)
    ap.add_argument("--steps", type=int, default=200)
    args = ap.parse_args()
    if args.quick:
        args.steps, args.d_model, args.device_threads = 10, 32, 1
    started = time.perf_counter()
    spec = {"type": "l1_chunk", "d_model": args.d_model, "n_layers": 4, "n_heads": 4, "chunk_size": 8}
    say(f"two trainings in workers forked from the fork server, on {args.device}")
    forked = run_pool(preloaded_fork_server(), 2, args, spec)
    say("one training in a spawned worker")
    (spawned,) = run_pool(multiprocessing.get_context("spawn"), 1, args, spec)
    preloaded = [name for name in preload_modules() if _importable(name)]
    entry = entry_of(
        started,
        run_environment(torch.device(args.device)),
        make_dataset(),
        args,
        forked=[{k: v for k, v in w.items() if k != "weights"} for w in forked],
        spawned={k: v for k, v in spawned.items() if k != "weights"},
        forked_vs_forked=difference(forked[0]["weights"], forked[1]["weights"]),
        forked_vs_spawned=difference(forked[0]["weights"], spawned["weights"]),
        preloaded=preloaded,
    )
    text = markdown(entry)
    print(text)
    write_results(args.results, STEM, entry, text)


def _importable(name: str) -> bool:
    """Whether this machine imports `name`: the server skips each preloaded module that it cannot."""
    try:
        __import__(name)
    except Exception:  # what the server does too (flows/runtime/fork_server._preload)
        return False
    return True


if __name__ == "__main__":
    main()
