"""The trainer on a GPU: throughput against one CPU thread, exact resume, and overhead over a plain loop.

The project's own machine has no GPU, so `trainer.train`'s CUDA path (the policy, its batches and its
generator on the device, the checkpointed CUDA RNG, a sync per step for the non-finite check) is only
exercised when a GPU machine is borrowed for a few minutes. This script checks it in one short run:

1. steps/s of `train` per built-in policy type on the device, and of the same training on the CPU with
   one thread in the same run (their ratio);
2. exact resume on the device: a run interrupted after a checkpoint (its `on_checkpoint` hook raises)
   and resumed ends with the same weights as an uninterrupted one? Two uninterrupted runs are compared
   too: on CUDA some kernels are not deterministic, and that difference is the floor a resume's can
   be judged against;
3. the overhead of `train` over a plain PyTorch loop on the device (the same model, batches, AdamW,
   schedule and clipping; alternating runs, whole calls timed).

The data is a small synthetic DemoDataset (actions a smooth function of the state), so no Meta-World
rollouts are needed. Everything runs on CPU too (`--device cpu --quick`: a dry run of under a minute).

    PYTHONPATH=. python benchmarks/bench_train_cuda.py --device cuda
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from bench_train import plain_loop  # run as a script: benchmarks/ is on sys.path

from capvector.core.policies.base import Policy, build_policy
from capvector.core.simulation.demos import DatasetMeta, DemoDataset
from capvector.core.training.device import resolve_device, run_environment
from capvector.core.training.trainer import TrainConfig, train

RESULTS = Path(__file__).resolve().parent / "results"
TYPES = ["l1_chunk", "flow"]


class Interrupted(BaseException):
    """The run going away after a checkpoint (like KeyboardInterrupt: nothing on the way catches it)."""


def make_dataset(episodes: int = 16, length: int = 50, seed: int = 0) -> DemoDataset:
    """A contract-shaped state DemoDataset whose actions are a smooth function of the state (learnable)."""
    g = torch.Generator().manual_seed(seed)
    n = episodes * length
    state = torch.randn(n, 39, generator=g)
    tensors = {
        "state": state,
        "proprio": state[:, :4].clone(),
        "action": torch.tanh(state[:, :4] + 0.5 * state[:, 35:39]),
        "episode": torch.arange(episodes).repeat_interleave(length),
        "step": torch.arange(length).repeat(episodes),
        "task": (torch.arange(episodes) % 2).repeat_interleave(length),
    }
    tasks = ["reach-v3", "push-v3"]
    meta = DatasetMeta(
        tasks=tasks,
        instructions=["reach to the goal", "push the puck to the goal"],
        obs_mode="state",
        camera="corner2",
        image_size=16,
        horizon=length,
        episodes_per_task=episodes // 2,
        seed_offset=0,
        seeds={t: list(range(episodes // 2)) for t in tasks},
        failures={t: 0 for t in tasks},
        n_episodes=episodes,
        n_steps=n,
    )
    return DemoDataset.create(tensors, meta)


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn: Callable[[], Any], device: torch.device) -> tuple[float, Any]:
    """Seconds of a whole call, the device's queued work included, and what it returned."""
    synchronize(device)
    start = time.perf_counter()
    out = fn()
    synchronize(device)
    return time.perf_counter() - start, out


class Bench:
    """One policy type's model, its starting weights and the configs of the runs; runs in a scratch dir."""

    def __init__(self, policy_type: str, args, dataset: DemoDataset, device: torch.device, work: Path):
        self.spec = {
            "type": policy_type,
            "d_model": args.d_model,
            "n_layers": 4,
            "n_heads": 4,
            "chunk_size": 8,
        }
        self.type, self.args, self.dataset, self.device, self.work = policy_type, args, dataset, device, work
        torch.manual_seed(0)
        self.initial = build_policy(self.spec, "cpu").state_dict()
        self.runs = 0

    def fresh(self) -> Policy:
        """The policy at its starting weights, on the CPU (train moves it)."""
        policy = build_policy(self.spec, "cpu")
        policy.load_state_dict(self.initial)
        return policy

    def config(self, steps: int, on_device: bool = True, **kw) -> TrainConfig:
        """A training run on the device (torch's default CPU thread count), or on the CPU with one thread."""
        base = dict(
            steps=steps,
            batch_size=self.args.batch_size,
            warmup_steps=steps // 10,
            checkpoint_every=self.args.checkpoint_every,
            log_every=10,
            device=str(self.device) if on_device else "cpu",
            num_threads=self.args.device_threads if on_device else 1,
        )
        return TrainConfig(**{**base, **kw})

    def run_dir(self, label: str) -> Path:
        self.runs += 1
        return self.work / f"{self.type}-{self.runs:03d}-{label}"

    def run(self, config: TrainConfig, label: str, run_dir: Path | None = None, **kw) -> dict:
        """A whole `train` call from the starting weights: its seconds, its result, the final weights."""
        policy = self.fresh()
        device = resolve_device(config.device)
        run_dir = run_dir or self.run_dir(label)
        seconds, result = timed(lambda: train(policy, self.dataset, config, run_dir, **kw), device)
        return {"seconds": seconds, "result": result, "weights": cpu_state(policy)}

    def plain(self, config: TrainConfig) -> float:
        policy = self.fresh()
        device = resolve_device(config.device)
        return timed(lambda: plain_loop(policy, self.dataset, config, device), device)[0]

    def warm_up(self) -> None:
        """Untimed: the first calls in a process pay lazy imports, CUDA context and kernel loading."""
        for on_device in (True, False):
            config = self.config(5, on_device, warmup_steps=1)
            self.run(config, "warm-up")
            self.plain(config)


def cpu_state(policy: Policy) -> dict[str, torch.Tensor]:
    return {k: v.detach().to("cpu").clone() for k, v in policy.state_dict().items()}


def difference(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> dict:
    """Largest absolute difference over all weights, and whether they are equal bit for bit."""
    assert a.keys() == b.keys()
    worst = max(((a[k].double() - b[k].double()).abs().max().item() for k in a if a[k].numel()), default=0.0)
    return {"max_abs_diff": worst, "bitwise_equal": all(torch.equal(a[k], b[k]) for k in a)}


def throughput(bench: Bench) -> dict:
    """Phase 1: steps/s of `train` on the device and on one CPU thread, whole calls and loop only."""
    out = {}
    for where, steps in (("device", bench.args.steps), ("cpu1", bench.args.cpu_steps)):
        run = bench.run(bench.config(steps, on_device=where == "device"), where)
        out[where] = {
            "steps": steps,
            "call_steps_per_s": round(steps / run["seconds"], 2),
            "loop_steps_per_s": round(run["result"].steps_per_s, 2),
            "final_loss": run["result"].final_loss,
        }
    for kind in ("call", "loop"):
        rate = f"{kind}_steps_per_s"
        out[f"{kind}_speedup"] = round(out["device"][rate] / out["cpu1"][rate], 2)
    return out


def resume(bench: Bench) -> dict:
    """Phase 2: interrupted after the checkpoint at half the steps and resumed, vs uninterrupted runs."""
    steps = bench.args.resume_steps
    at = steps // 2
    config = bench.config(steps, checkpoint_every=at, seed=7)
    straight = bench.run(config, "straight")
    again = bench.run(config, "straight-again")

    def interrupt(step: int, folder: Path) -> None:
        if step == at:
            raise Interrupted(f"interrupted after the checkpoint at step {step}")

    run_dir = bench.run_dir("interrupted")
    try:
        bench.run(config, "interrupted", run_dir, on_checkpoint=interrupt)
        raise RuntimeError("the run was not interrupted")
    except Interrupted:
        pass
    resumed = bench.run(config, "resumed", run_dir)
    return {
        "steps": steps,
        "interrupted_after": at,
        "resumed_from_step": resumed["result"].resumed_from_step,
        "resumed_vs_straight": difference(resumed["weights"], straight["weights"]),
        "straight_vs_straight": difference(again["weights"], straight["weights"]),
    }


def overhead(bench: Bench) -> dict:
    """Phase 3: `train` vs the plain loop on the device, alternating; the median of paired ratios."""
    config = bench.config(bench.args.steps)
    times: dict[str, list[float]] = {"ours": [], "plain": []}
    for r in range(bench.args.rounds):
        for which in ["ours", "plain"] if r % 2 == 0 else ["plain", "ours"]:
            seconds = bench.run(config, "ours")["seconds"] if which == "ours" else bench.plain(config)
            times[which].append(seconds)
    paired = [o / p - 1.0 for o, p in zip(times["ours"], times["plain"], strict=True)]
    steps = bench.args.steps * bench.args.rounds
    return {
        "steps": bench.args.steps,
        "rounds": bench.args.rounds,
        "ours_steps_per_s": round(steps / sum(times["ours"]), 2),
        "plain_steps_per_s": round(steps / sum(times["plain"]), 2),
        "ours_seconds": [round(t, 3) for t in times["ours"]],
        "plain_seconds": [round(t, 3) for t in times["plain"]],
        "overhead": round(sorted(paired)[len(paired) // 2], 4),
        "overhead_per_round": [round(x, 4) for x in paired],
    }


def say(line: str) -> None:
    print(line, flush=True)


def measure(policy_type: str, args, dataset: DemoDataset, device: torch.device, work: Path) -> dict:
    bench = Bench(policy_type, args, dataset, device, work)
    bench.warm_up()
    speed = throughput(bench)
    on, cpu = speed["device"], speed["cpu1"]
    say(
        f"[1/3 throughput] {policy_type}: {device} {rates(on)}, cpu 1 thread {rates(cpu)}, "
        f"x{speed['loop_speedup']:.1f} (call x{speed['call_speedup']:.1f})"
    )
    exact = resume(bench)
    say(
        f"[2/3 resume] {policy_type}: resumed from step {exact['resumed_from_step']}; "
        f"resumed vs straight {compared(exact['resumed_vs_straight'])}; "
        f"straight vs straight {compared(exact['straight_vs_straight'])}"
    )
    cost = overhead(bench)
    say(
        f"[3/3 overhead] {policy_type}: ours {cost['ours_steps_per_s']:.1f} steps/s, plain "
        f"{cost['plain_steps_per_s']:.1f}, overhead {cost['overhead']:+.1%} (per round {per_round(cost)})"
    )
    params = sum(p.numel() for p in bench.fresh().parameters())
    return {"params": params, "throughput": speed, "resume": exact, "overhead": cost}


def rates(run: dict) -> str:
    return f"{run['loop_steps_per_s']:.1f} steps/s (call {run['call_steps_per_s']:.1f})"


def compared(diff: dict) -> str:
    return (
        f"max diff {diff['max_abs_diff']:.3g}, {'bitwise equal' if diff['bitwise_equal'] else 'not bitwise'}"
    )


def per_round(cost: dict) -> str:
    return ", ".join(f"{x:+.1%}" for x in cost["overhead_per_round"])


def throughput_row(policy_type: str, e: dict) -> str:
    speed = e["throughput"]
    return (
        f"| {policy_type} | {e['params']:,} | {rates(speed['device'])} | {rates(speed['cpu1'])} | "
        f"x{speed['loop_speedup']:.1f} (call x{speed['call_speedup']:.1f}) |\n"
    )


def resume_row(policy_type: str, e: dict) -> str:
    exact = e["resume"]
    return (
        f"| {policy_type} | {exact['steps']} | {exact['interrupted_after']} | {exact['resumed_from_step']} | "
        f"{compared(exact['resumed_vs_straight'])} | {compared(exact['straight_vs_straight'])} |\n"
    )


def overhead_row(policy_type: str, e: dict) -> str:
    cost = e["overhead"]
    return (
        f"| {policy_type} | {cost['steps']} x {cost['rounds']} | {cost['ours_steps_per_s']:.1f} | "
        f"{cost['plain_steps_per_s']:.1f} | {cost['overhead']:+.1%} | {per_round(cost)} |\n"
    )


def markdown(entry: dict) -> str:
    env, args, policies = entry["environment"], entry["args"], entry["policies"]

    def rows(row: Callable[[str, dict], str]) -> str:
        return "".join(row(t, e) for t, e in policies.items())

    return (
        "# Training on a GPU (the trainer's CUDA path)\n\n"
        f"{entry['date']}: {env['device']} ({env['device_name']}), torch {env['torch']}, CUDA "
        f"{env['cuda_version']}, Python {entry['python']}, {args['device_threads']} torch CPU thread(s)\n"
        f"beside the device. Model: state, d={args['d_model']}, 4 layers, K=8, batch {args['batch_size']};\n"
        f"synthetic state demos ({entry['dataset_steps']} steps). `benchmarks/bench_train_cuda.py`.\n\n"
        "## 1. Throughput: device vs one CPU thread\n\n"
        "Steps/s of the training loop (`TrainResult.steps_per_s`), and of the whole `train` call (set-up,\n"
        f"checkpoints every {args['checkpoint_every']} steps and the final save included); {args['steps']} "
        f"steps on the device, {args['cpu_steps']} on the CPU.\n\n"
        "| policy | params | device | CPU, 1 thread | speed-up |\n"
        "|---|---|---|---|---|\n" + rows(throughput_row) + "\n"
        "## 2. Exact resume on the device\n\n"
        "A run whose `on_checkpoint` raises after the checkpoint at half its steps, then resumed in the\n"
        "same run dir, against an uninterrupted run; two uninterrupted runs against each other give the\n"
        "floor set by non-deterministic kernels. Max diff: the largest absolute difference of any weight.\n\n"
        "| policy | steps | interrupted after | resumed from | resumed vs straight | straight vs straight |\n"
        "|---|---|---|---|---|---|\n" + rows(resume_row) + "\n"
        "## 3. Overhead of `train` over a plain loop on the device\n\n"
        "Same model and initial weights, same batches (the policy's batcher), AdamW, schedule and clipping;\n"
        "alternating runs, whole calls timed (the device synchronised at both ends). Overhead: the median\n"
        "over rounds of (our time / plain time - 1).\n\n"
        "| policy | steps x rounds | ours steps/s | plain steps/s | overhead | per round |\n"
        "|---|---|---|---|---|---|\n" + rows(overhead_row)
    )


def add_device_options(ap: argparse.ArgumentParser, stem: str) -> None:
    """The options every GPU benchmark here takes: device, model size, threads, dry run, results folder."""
    ap.add_argument("--device", default="cuda", help="the device checked: cuda, cuda:N or cpu (default cuda)")
    ap.add_argument("--batch-size", type=int, default=64)
    ap.add_argument("--d-model", type=int, default=128)
    ap.add_argument("--checkpoint-every", type=int, default=100)
    ap.add_argument(
        "--device-threads",
        type=int,
        default=torch.get_num_threads(),
        help="torch CPU threads of the runs on the device (default: torch's count here)",
    )
    ap.add_argument("--quick", action="store_true", help="a CPU dry run: a few steps, d_model 32, 1 thread")
    ap.add_argument("--results", type=Path, default=RESULTS, help=f"where {stem}.{{md,json}} go")


def entry_of(started: float, env: dict, dataset: DemoDataset, args: argparse.Namespace, **measured) -> dict:
    """A benchmark run's record: when, where, on what, with which options, what it measured, how long."""
    return {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "python": platform.python_version(),
        "environment": env,
        "dataset_steps": len(dataset),
        "args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
        **measured,
        "seconds": round(time.perf_counter() - started, 1),
    }


def write_results(results: Path, stem: str, entry: dict, markdown_text: str) -> None:
    results.mkdir(parents=True, exist_ok=True)
    (results / f"{stem}.json").write_text(json.dumps(entry, indent=1) + "\n")
    (results / f"{stem}.md").write_text(markdown_text)
    say(f"wrote {results / f'{stem}.md'} and {stem}.json ({entry['seconds']:.0f} s in all)")


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_device_options(ap, "train_cuda")
    ap.add_argument("--steps", type=int, default=300, help="steps per timed run on the device")
    ap.add_argument(
        "--cpu-steps", type=int, default=None, help="steps of the 1-thread CPU run (default: --steps)"
    )
    ap.add_argument("--resume-steps", type=int, default=100, help="steps of the resume check's runs")
    ap.add_argument("--rounds", type=int, default=3, help="alternating rounds of the overhead phase")
    args = ap.parse_args()
    if args.quick:
        args.steps, args.cpu_steps, args.resume_steps, args.rounds, args.d_model = 10, 10, 8, 1, 32
        args.device_threads = 1  # a shared CPU crawls with more
    args.cpu_steps = args.cpu_steps or args.steps
    return args


def main() -> None:
    started = time.perf_counter()
    args = parse_args()
    device = resolve_device(args.device)
    env = run_environment(device)
    say(f"[0/3] {env['device']} ({env['device_name']}), torch {env['torch']}, CUDA {env['cuda_version']}")
    dataset = make_dataset()
    work = Path(tempfile.mkdtemp(prefix="bench-train-cuda-"))
    try:
        policies = {t: measure(t, args, dataset, device, work) for t in TYPES}
    finally:
        shutil.rmtree(work, ignore_errors=True)
    entry = entry_of(started, env, dataset, args, policies=policies)
    print(json.dumps(entry, indent=1))
    write_results(args.results, "train_cuda", entry, markdown(entry))


if __name__ == "__main__":
    main()
