"""Benchmark: the cost of recording per-patch 3D targets (`patch_xyz`) in pixels demo collection.

(a) Whole demo steps: the scripted expert's episodes in one process (env step + expert + observation),
    64x64 `corner2` images, RGB only (`patch_grid=None`) against RGB + depth render + back-projection
    + patch medians (`patch_grid=4`, the default policy's 4x4 token grid). Same tasks and seeds; the
    two alternate in order over `ROUNDS` rounds, medians reported (the machine is shared).
(b) The observation alone on a fixed simulator state: RGB render, RGB + depth render, back-projection
    and patch medians, and, for reference, what reading the depth buffer of the RGB pass would cost
    (one `mjr_render`, both buffers read; needs mujoco.Renderer's private members, so it is only
    measured here, not used).

    python benchmarks/bench_depth_targets.py
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import statistics
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
from mujoco import _render  # noqa: E402

from capvector.core.simulation.demos import expert_episode, library_versions  # noqa: E402
from capvector.core.simulation.depth_targets import patch_xyz  # noqa: E402
from capvector.core.simulation.envs import EnvConfig, MetaWorldEnv  # noqa: E402

TASKS = ["reach-v3", "push-v3", "drawer-close-v3"]
SEEDS = [0, 1]
ROUNDS = 5
SIZE, GRID, CAMERA = 64, 4, "corner2"
CALLS = 200
RESULTS = Path(__file__).resolve().parent / "results"


def episodes(envs: dict[str, MetaWorldEnv]) -> tuple[int, float]:
    steps, start = 0, time.perf_counter()
    for task in TASKS:
        for seed in SEEDS:
            episode = expert_episode(envs[task], seed)
            steps += len(episode["action"]) if episode is not None else envs[task].steps
    return steps, time.perf_counter() - start


def bench_steps() -> dict:
    def make(grid: int | None) -> dict[str, MetaWorldEnv]:
        return {
            t: MetaWorldEnv(
                EnvConfig(task=t, obs_mode="pixels", image_size=SIZE, camera=CAMERA, patch_grid=grid)
            )
            for t in TASKS
        }

    arms = {"rgb": make(None), "rgb+patch_xyz": make(GRID)}
    for envs in arms.values():
        episodes(envs)  # warm: GL contexts, first renders
    per_step: dict[str, list[float]] = {name: [] for name in arms}
    steps = {}
    for r in range(ROUNDS):
        order = list(arms) if r % 2 == 0 else list(reversed(arms))
        for name in order:
            n, wall = episodes(arms[name])
            steps[name] = n
            per_step[name].append(wall / n * 1e3)
    for envs in arms.values():
        for env in envs.values():
            env.close()
    assert steps["rgb"] == steps["rgb+patch_xyz"], steps  # same episodes: the targets change no action
    med = {name: statistics.median(v) for name, v in per_step.items()}
    return {
        "steps_per_round": steps["rgb"],
        "ms_per_step": {k: round(v, 3) for k, v in med.items()},
        "all_rounds_ms": {k: [round(x, 3) for x in v] for k, v in per_step.items()},
        "ratio": round(med["rgb+patch_xyz"] / med["rgb"], 3),
    }


def timed(fn, calls: int = CALLS) -> float:
    fn()
    start = time.perf_counter()
    for _ in range(calls):
        fn()
    return (time.perf_counter() - start) / calls * 1e3


def bench_observation() -> dict:
    env = MetaWorldEnv(EnvConfig(task="pick-place-v3", obs_mode="pixels", image_size=SIZE, camera=CAMERA))
    env.reset(0)
    fast = env._fast_renderer()
    data = env.env.data
    _, depth, camera = fast.render_rgbd(data)
    r = fast._renderer

    def one_pass() -> None:  # reference only: depth read from the RGB pass (private Renderer members)
        r.update_scene(data, camera=CAMERA)
        _render.mjr_render(r._rect, r._scene, r._mjr_context)
        rgb, z = np.empty((SIZE, SIZE, 3), np.uint8), np.empty((SIZE, SIZE), np.float32)
        _render.mjr_readPixels(rgb, z, r._rect, r._mjr_context)

    rows = {}
    for _ in range(3):  # interleaved, medians: the machine is shared
        for name, fn in (
            ("rgb render", lambda: fast.render(data)),
            ("rgb + depth render", lambda: fast.render_rgbd(data)),
            ("back-projection + patch medians", lambda: patch_xyz(depth, camera, GRID, fast.far)),
            ("(reference) one pass, both buffers read", one_pass),
        ):
            rows.setdefault(name, []).append(timed(fn))
    env.close()
    return {name: round(statistics.median(v), 3) for name, v in rows.items()}


def main() -> None:
    result = {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, MUJOCO_GL={os.environ['MUJOCO_GL']}",
        "versions": library_versions(),
        "setup": {
            "tasks": TASKS,
            "seeds": SEEDS,
            "rounds": ROUNDS,
            "image": SIZE,
            "grid": GRID,
            "camera": CAMERA,
        },
        "steps": bench_steps(),
        "observation_ms": bench_observation(),
    }
    print(json.dumps(result, indent=1))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "depth_targets.json").write_text(json.dumps(result, indent=1) + "\n")
    s, o = result["steps"], result["observation_ms"]
    image_bytes, patch_bytes = SIZE * SIZE * 3, GRID * GRID * 3 * 4
    lines = [
        "# Per-patch 3D targets (`patch_xyz`): cost in pixels demo collection",
        "",
        f"{result['date']}, {result['machine']}, mujoco {result['versions']['mujoco']}; "
        "`python benchmarks/bench_depth_targets.py`. The machine was shared with other jobs.",
        "",
        f"## Whole demo steps ({', '.join(TASKS)}; seeds {SEEDS}; "
        f"{SIZE}x{SIZE} `{CAMERA}`, grid {GRID}x{GRID})",
        "",
        f"One process, scripted expert, {s['steps_per_round']} steps per round, {ROUNDS} rounds in "
        "alternating order, median ms per step (env step + expert + observation):",
        "",
        "| observation | ms / step | ratio |",
        "|---|---|---|",
        f"| image (RGB only) | {s['ms_per_step']['rgb']} | 1.00 |",
        f"| image + `patch_xyz` (depth pass, back-projection, medians) | "
        f"{s['ms_per_step']['rgb+patch_xyz']} | **{s['ratio']:.2f}** |",
        "",
        f"Per-round ms/step: RGB {s['all_rounds_ms']['rgb']}, "
        f"with `patch_xyz` {s['all_rounds_ms']['rgb+patch_xyz']}.",
        "",
        f"## The observation alone (pick-place-v3, one state, median of 3 x {CALLS} calls)",
        "",
        "| part | ms |",
        "|---|---|",
        *[f"| {name} | {ms} |" for name, ms in o.items()],
        "",
        "The depth pass is MuJoCo's own (`Renderer.enable_depth_rendering`: a second, unlit `mjr_render`).",
        "Reading the depth buffer of the RGB pass instead would make depth almost free (last row) but needs",
        "mujoco.Renderer's private members, and that pass draws the sky box at a finite depth, so background",
        "pixels would need another test than the far plane; not done.",
        "",
        f"Storage: {patch_bytes} bytes of `patch_xyz` per step beside a {image_bytes}-byte image "
        f"(+{100 * patch_bytes / image_bytes:.1f} %).",
        "",
    ]
    (RESULTS / "depth_targets.md").write_text("\n".join(lines))


if __name__ == "__main__":
    main()
