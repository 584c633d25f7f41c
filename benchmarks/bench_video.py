"""Benchmark: what recording one evaluation episode as a video costs, old (64 px GIF) against new (mp4).

One real Meta-World episode (scripted expert, `STEPS` steps, `corner2`), rendered and written by each
arm: the old recorder (frames from the policy's 64 px renderer, a looping GIF written by PIL, as
`write_gif` did before mp4s) and the new one (frames from a renderer of the video size, an mp4
written by `capvector.core.evaluation.video.write_mp4`: imageio's ffmpeg plugin, H.264, one thread).
The episode without any frames is the reference the recording adds to. Arms alternate over `ROUNDS`
rounds; medians are reported (the machine is shared).

    nice -n 19 python benchmarks/bench_video.py
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402

from capvector.core.evaluation.video import VIDEO_FPS, write_mp4  # noqa: E402
from capvector.core.simulation.demos import EVAL_SEED_BASE, library_versions  # noqa: E402
from capvector.core.simulation.envs import EnvConfig, MetaWorldEnv, expert_action  # noqa: E402

TASK, CAMERA, STEPS, ROUNDS = "drawer-close-v3", "corner2", 150, 5
POLICY_SIZE = 64
RESULTS = Path(__file__).resolve().parent / "results"


def write_gif(frames: list[np.ndarray], path: Path, fps: int = 25) -> Path:
    """The recorder before mp4s (capvector_core/evaluation/rollouts.py until then), kept here to time it."""
    from PIL import Image

    images = [Image.fromarray(frame) for frame in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=1000 // fps, loop=0)
    return path


def episode(env: MetaWorldEnv, size: int | None) -> tuple[list[np.ndarray], float, float]:
    """The episode's frames at `size` (None: none), its wall time and the part spent rendering them."""
    rendering, frames = 0.0, []
    start = time.perf_counter()
    state = env.reset_state(EVAL_SEED_BASE)
    for step in range(STEPS + 1):
        if size is not None:
            t = time.perf_counter()
            frames.append(env.render(size))
            rendering += time.perf_counter() - t
        if step < STEPS:
            state = env.step_state(expert_action(TASK, state))[0]
    return frames, time.perf_counter() - start, rendering


def arms() -> dict[str, tuple[int | None, Callable[[list[np.ndarray], Path], Path] | None, str]]:
    return {
        "no video (reference)": (None, None, ""),
        f"GIF {POLICY_SIZE} px (before)": (POLICY_SIZE, write_gif, ".gif"),
        "mp4 224 px": (224, write_mp4, ".mp4"),
        "mp4 256 px (default)": (256, write_mp4, ".mp4"),
    }


def measure(env: MetaWorldEnv, folder: Path) -> dict[str, dict[str, list[float]]]:
    rows: dict[str, dict[str, list[float]]] = {name: {} for name in arms()}
    for r in range(ROUNDS + 1):  # round 0 warms GL contexts, renderers and the encoder check
        order = list(arms()) if r % 2 else list(reversed(arms()))
        for name in order:
            size, writer, suffix = arms()[name]
            frames, wall, rendering = episode(env, size)
            encoding, nbytes = 0.0, 0
            if writer is not None:
                t = time.perf_counter()
                path = writer(frames, folder / f"episode{suffix}")
                encoding, nbytes = time.perf_counter() - t, path.stat().st_size
            if r == 0:
                continue
            for key, value in (("episode_s", wall), ("render_s", rendering), ("encode_s", encoding)):
                rows[name].setdefault(key, []).append(value)
            rows[name]["bytes"] = [nbytes]
    return rows


def summary(rows: dict[str, dict[str, list[float]]]) -> dict[str, dict[str, float]]:
    med = {name: {k: statistics.median(v) for k, v in cols.items()} for name, cols in rows.items()}
    reference = med["no video (reference)"]["episode_s"]
    out = {}
    for name, m in med.items():
        added = m["episode_s"] - reference + m["encode_s"]  # what recording adds to the episode
        out[name] = {
            "render_ms": round(1e3 * m["render_s"], 1),
            "encode_ms": round(1e3 * m["encode_s"], 1),
            "episode_ms": round(1e3 * m["episode_s"], 1),
            "added_ms": round(1e3 * added, 1),
            "kib": round(m["bytes"] / 1024, 1),
        }
    return out


def markdown(result: dict) -> str:
    s = result["arms"]
    old, new = s[f"GIF {POLICY_SIZE} px (before)"], s["mp4 256 px (default)"]
    render_ratio = new["render_ms"] / old["render_ms"]
    lines = [
        "# Rollout videos: cost of recording one episode, 64 px GIF (before) against mp4",
        "",
        f"{result['date']}, {result['machine']}, mujoco {result['versions']['mujoco']}; "
        "`nice -n 19 python benchmarks/bench_video.py`. The machine was shared with other jobs.",
        "",
        f"One {TASK} episode of {STEPS} expert steps ({STEPS + 1} frames, `{CAMERA}`), {ROUNDS} rounds "
        "in alternating order, medians. *render*: the frames' renders; *encode*: writing the file; "
        "*added*: the episode's wall time over the reference, plus encoding: what recording costs.",
        "",
        "| recorder | render ms | encode ms | episode ms | added ms | file KiB |",
        "|---|---|---|---|---|---|",
        *[
            f"| {name} | {r['render_ms']} | {r['encode_ms']} | {r['episode_ms']} | {r['added_ms']} "
            f"| {r['kib']} |"
            for name, r in s.items()
        ],
        "",
        f"mp4 256 px against GIF 64 px: **{new['added_ms'] / old['added_ms']:.2f}x** the added time "
        f"({new['added_ms']} against {old['added_ms']} ms per episode of {STEPS} steps), "
        f"{new['kib'] / old['kib']:.2f}x the file size. mp4s play at {VIDEO_FPS} fps (Meta-World's "
        "real time); the GIFs were written at 25 fps.",
        "",
        "Rendering is most of the cost, and it is software rendering here (llvmpipe draws on the CPU; its "
        f"cost grows far less than the pixel count: 16x the pixels, {render_ratio:.2f}x "
        "the render time); the encoder (libx264, one thread) costs less than PIL's GIF quantizer did at "
        "64 px. Only recorded episodes (`--video N`: N per task) pay this; the others render no frames. "
        "Round-to-round spread on this shared machine is large (`video.json` has every round).",
        "",
    ]
    return "\n".join(lines)


def gl_renderer(env: MetaWorldEnv) -> str:
    """The OpenGL renderer MuJoCo draws with (llvmpipe: software, on the CPU)."""
    from OpenGL import GL

    env.render()  # makes its context current
    return GL.glGetString(GL.GL_RENDERER).decode()


def main() -> None:
    env = MetaWorldEnv(EnvConfig(task=TASK, camera=CAMERA, image_size=POLICY_SIZE, horizon=STEPS))
    try:
        with tempfile.TemporaryDirectory() as folder:
            rows = measure(env, Path(folder))
        gl = gl_renderer(env)
    finally:
        env.close()
    result = {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, MUJOCO_GL={os.environ['MUJOCO_GL']} "
        f"({gl})",
        "versions": library_versions(),
        "setup": {"task": TASK, "camera": CAMERA, "steps": STEPS, "rounds": ROUNDS},
        "arms": summary(rows),
        "all_rounds_s": rows,
    }
    print(json.dumps(result["arms"], indent=1))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "video.json").write_text(json.dumps(result, indent=1) + "\n")
    (RESULTS / "video.md").write_text(markdown(result))


if __name__ == "__main__":
    main()
