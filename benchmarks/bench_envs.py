"""Benchmark (a) expert demo collection steps/s, state and pixels (64x64), 1 vs 2 processes, and
(c) evaluation env-steps/s of `evaluate(expert_action_fn)` against a plain loop stepping the same
Meta-World environments (same tasks, seeds, horizon, early stop at success) with the scripted expert.

All timings are whole calls, set-up included (env construction; worker start-up for 2 processes).
(c) runs each loop once untimed (a process compiles a task's XML once, for whichever loop comes
first), then rotates their order for `ROUNDS` rounds and reports medians: the machine is shared.

    python benchmarks/bench_envs.py
"""

from __future__ import annotations

import datetime
import json
import multiprocessing
import os
import platform
import statistics
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from capvector.core.evaluation.rollouts import EvalConfig, evaluate, expert_action_fn  # noqa: E402
from capvector.core.simulation.demos import DemoConfig, collect_demos, library_versions  # noqa: E402
from capvector.core.simulation.envs import MetaWorldEnv, expert_policy  # noqa: E402

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
RESULTS = Path(__file__).resolve().parent / "results"
ROUNDS = 9


def bench_collection(obs_mode: str, tasks: list[str], episodes: int, workers: int) -> dict:
    config = DemoConfig(tasks=tasks, episodes_per_task=episodes, obs_mode=obs_mode, workers=workers)
    start = time.perf_counter()
    dataset = collect_demos(config)
    wall = time.perf_counter() - start
    return {
        "obs_mode": obs_mode,
        "workers": workers,
        "tasks": len(tasks),
        "episodes": dataset.meta.n_episodes,
        "steps": len(dataset),
        "wall_s": round(wall, 2),
        "steps_per_s": round(len(dataset) / wall, 1),
        "content_hash": dataset.content_hash[:12],
    }


def plain_expert_loop(config: EvalConfig) -> tuple[int, int]:
    """One raw metaworld env per task (built by `MetaWorldEnv`, as evaluate's are: same simulator
    settings), the expert called directly on its float64 observation."""
    steps = successes = 0
    for task in config.tasks:
        wrapper = MetaWorldEnv(config.env_config(task))
        env, policy = wrapper.env, expert_policy(task)
        for seed in config.seeds:
            env.seed(seed)
            obs, _ = env.reset()
            for _ in range(config.horizon):
                obs, _, _, _, info = env.step(policy.get_action(obs).clip(-1, 1))
                steps += 1
                if info["success"]:
                    successes += 1
                    break
        wrapper.close()
    return steps, successes


def _timed(fn):
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - wall, time.process_time() - cpu


def bench_evaluation(episodes: int, rounds: int = ROUNDS) -> dict:
    """`evaluate` as configured (all episodes in one batch), `evaluate` one episode at a time (same
    code, no lockstep: splits evaluation overhead from the cost of stepping many envs in turn), and
    the plain loop; every round checks that each loop computed what it did in the warm-up."""
    config = EvalConfig(tasks=TASKS, episodes_per_task=episodes, batch_size=len(TASKS) * episodes)
    one_at_a_time = config.model_copy(update={"batch_size": 1})
    loops = {
        "evaluate": lambda: evaluate(expert_action_fn, config).episodes,
        "evaluate_batch_1": lambda: evaluate(expert_action_fn, one_at_a_time).episodes,
        "plain": lambda: plain_expert_loop(config),
    }
    expected = {name: loop() for name, loop in loops.items()}  # untimed warm-up of every loop
    assert expected["evaluate"] == expected["evaluate_batch_1"]
    plain_steps, plain_successes = expected["plain"]
    eval_steps = sum(r.steps for r in expected["evaluate"])
    load_start = " ".join(f"{x:.1f}" for x in os.getloadavg())
    wall: dict[str, list[float]] = {name: [] for name in loops}
    cpu: dict[str, list[float]] = {name: [] for name in loops}
    for i in range(rounds):
        names = list(loops)[i % len(loops) :] + list(loops)[: i % len(loops)]
        for name in names:
            out, seconds, cpu_seconds = _timed(loops[name])
            if out != expected[name]:
                raise RuntimeError(f"{name} computed something else in round {i}")
            wall[name].append(seconds)
            cpu[name].append(cpu_seconds)
        print(f"round {i}: " + ", ".join(f"{name} {wall[name][-1]:.2f} s" for name in loops), flush=True)
    rows = {}
    for name in loops:
        steps = plain_steps if name == "plain" else eval_steps
        pairs = zip(wall[name], wall["plain"], strict=True)
        rows[name] = {
            "env_steps": steps,
            "wall_s": round(statistics.median(wall[name]), 2),
            "cpu_s": round(statistics.median(cpu[name]), 2),
            "steps_per_s": round(steps / statistics.median(wall[name]), 1),
            "ratio": round(statistics.median((steps / w) / (plain_steps / p) for w, p in pairs), 3),
            "ratio_cpu": round(
                (steps / statistics.median(cpu[name])) / (plain_steps / statistics.median(cpu["plain"])), 3
            ),
        }
    return {
        "tasks": len(TASKS),
        "episodes_per_task": episodes,
        "batch_size": config.batch_size,
        "rounds": rounds,
        "load_average_start": load_start,
        "load_average_end": " ".join(f"{x:.1f}" for x in os.getloadavg()),
        "evaluate_success": sum(r.success for r in expected["evaluate"]) / len(expected["evaluate"]),
        "plain_success": plain_successes / (len(TASKS) * episodes),
        "loops": rows,
        "ratio": rows["evaluate"]["ratio"],
        "rounds_wall_s": {name: [round(v, 2) for v in values] for name, values in wall.items()},
        "rounds_cpu_s": {name: [round(v, 2) for v in values] for name, values in cpu.items()},
    }


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    system = f"{platform.system()} {platform.release()}, Python {platform.python_version()}"
    return f"{cpu}, {os.cpu_count()} cores, {system}"


def _noop(x: int) -> int:
    return x


def spawn_startup_s() -> float:
    """Fixed cost of 2 spawned workers: a fresh interpreter re-importing this script (torch included)."""
    start = time.perf_counter()
    with multiprocessing.get_context("spawn").Pool(2) as pool:
        pool.map(_noop, [0, 1])
    return round(time.perf_counter() - start, 2)


def write_results(collection: list[dict], evaluation: dict, startup: float, load: str) -> None:
    date = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    payload = {
        "date": date,
        "machine": machine(),
        "versions": library_versions(),
        "load_average_at_start": load,
        "spawn_startup_s": startup,
        "collection": collection,
        "evaluation": evaluation,
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "envs.json").write_text(json.dumps(payload, indent=1) + "\n")
    lines = [
        "# Environments, demo collection and evaluation",
        "",
        f"{date}; {machine()}; MUJOCO_GL={os.environ['MUJOCO_GL']}.",
        "Produced by `python benchmarks/bench_envs.py`. The machine is shared with other work (load average "
        f"{load} at the start), so absolute numbers vary between runs.",
        "",
        "## (a) Expert demo collection (wall time includes env construction and worker start-up)",
        "",
        "| obs mode | processes | tasks | episodes | steps | wall s | steps/s |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in collection:
        lines.append(
            f"| {row['obs_mode']} | {row['workers']} | {row['tasks']} | {row['episodes']} | {row['steps']} "
            f"| {row['wall_s']} | {row['steps_per_s']} |"
        )
    e = evaluation
    lines += [
        "",
        f"Start-up of 2 spawned worker processes alone (interpreter + imports, no work): {startup} s; it is "
        "included in every 2-process row and is a fixed cost per `collect_demos` call.",
    ]
    lines += [
        "",
        "## (c) Evaluation throughput, state mode, scripted expert, same run",
        "",
        f"{e['tasks']} tasks x {e['episodes_per_task']} evaluation seeds, horizon 500, early stop at "
        f"success. `evaluate` steps all {e['batch_size']} envs together with one batched "
        "`expert_action_fn` call per step; with batch size 1 the same code runs one episode at a time. "
        "The plain loop steps one raw Meta-World env per task, built as `evaluate` builds its envs (from "
        "the compiled model cached per process, MuJoCo's BVH viewer flag off), with the expert called on "
        f"its float64 observation. After one untimed call of each, {e['rounds']} rounds rotate which loop "
        f"goes first; medians over rounds (load average {e['load_average_start']} before, "
        f"{e['load_average_end']} after). Success: evaluate {e['evaluate_success']:.3f}, plain "
        f"{e['plain_success']:.3f}.",
        "",
        "| loop | env-steps | wall s | CPU s | env-steps/s | vs plain (wall) | vs plain (CPU) |",
        "|---|---|---|---|---|---|---|",
    ]
    names = {
        "evaluate": f"`evaluate(expert_action_fn)`, batch {e['batch_size']}",
        "evaluate_batch_1": "`evaluate(expert_action_fn)`, batch 1",
        "plain": "plain loop (raw env + expert)",
    }
    for key, row in e["loops"].items():
        lines.append(
            f"| {names[key]} | {row['env_steps']} | {row['wall_s']} | {row['cpu_s']} | {row['steps_per_s']} "
            f"| {row['ratio']} | {row['ratio_cpu']} |"
        )
    lines += [
        "",
        f"**Ratio evaluate / plain (env-steps/s, median of the per-round ratios): {e['ratio']}** "
        "(target >= 0.9).",
        "",
    ]
    (RESULTS / "envs.md").write_text("\n".join(lines))


def main() -> None:
    load = " ".join(f"{x:.1f}" for x in os.getloadavg())
    startup = spawn_startup_s()
    print("spawn start-up s", startup, "load", load, flush=True)
    collection = []
    for obs_mode, tasks, episodes in [("state", TASKS, 25), ("pixels", TASKS, 3)]:
        for workers in (1, 2):
            row = bench_collection(obs_mode, tasks, episodes, workers)
            print(row, flush=True)
            collection.append(row)
    evaluation = bench_evaluation(episodes=10)
    print(evaluation, flush=True)
    write_results(collection, evaluation, startup, load)


if __name__ == "__main__":
    main()
