"""Benchmark (a) expert demo collection steps/s, state and pixels (64x64), 1 vs 2 processes, and
(c) evaluation env-steps/s of `evaluate(expert_action_fn)` against a plain loop stepping the same
Meta-World environments (same tasks, seeds, horizon, early stop at success) with the scripted expert.

All timings are whole calls, set-up included (env construction; worker start-up for 2 processes).

    python benchmarks/bench_envs.py
"""

from __future__ import annotations

import datetime
import json
import multiprocessing
import os
import platform
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from capvector_core.demos import DemoConfig, collect_demos, library_versions  # noqa: E402
from capvector_core.envs import MetaWorldEnv, expert_policy  # noqa: E402
from capvector_core.evaluation import EvalConfig, evaluate, expert_action_fn  # noqa: E402

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


def plain_expert_loop(config: EvalConfig) -> tuple[int, float, int]:
    """One raw metaworld env per task, the expert called directly on its float64 observation."""
    start = time.perf_counter()
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
    return steps, time.perf_counter() - start, successes


def bench_evaluation(episodes: int) -> dict:
    config = EvalConfig(tasks=TASKS, episodes_per_task=episodes, batch_size=len(TASKS) * episodes)
    result = evaluate(expert_action_fn, config)
    plain_steps, plain_wall, plain_successes = plain_expert_loop(config)
    ours = result.env_steps / result.wall_time_s
    plain = plain_steps / plain_wall
    return {
        "tasks": len(TASKS),
        "episodes_per_task": episodes,
        "batch_size": config.batch_size,
        "evaluate_env_steps": result.env_steps,
        "evaluate_wall_s": round(result.wall_time_s, 2),
        "evaluate_steps_per_s": round(ours, 1),
        "evaluate_success": result.mean_success,
        "plain_env_steps": plain_steps,
        "plain_wall_s": round(plain_wall, 2),
        "plain_steps_per_s": round(plain, 1),
        "plain_success": plain_successes / (len(TASKS) * episodes),
        "ratio": round(ours / plain, 3),
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
        f"success; `evaluate` steps all {e['batch_size']} envs together with one batched "
        "`expert_action_fn` call per step.",
        "",
        "| loop | env-steps | wall s | env-steps/s | success |",
        "|---|---|---|---|---|",
        f"| `evaluate(expert_action_fn)` | {e['evaluate_env_steps']} | {e['evaluate_wall_s']} "
        f"| {e['evaluate_steps_per_s']} | {e['evaluate_success']:.3f} |",
        f"| plain loop (raw env + expert) | {e['plain_env_steps']} | {e['plain_wall_s']} "
        f"| {e['plain_steps_per_s']} | {e['plain_success']:.3f} |",
        "",
        f"**Ratio evaluate / plain: {e['ratio']}** (target >= 0.7).",
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
