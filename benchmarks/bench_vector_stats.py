"""Benchmark: peak RSS of `capvector vector stats` on a large single-tensor vector, before/after streaming.

One float32 vector of one tensor (1 GiB by default: 2^28 elements), written in pieces (the script never
holds it). Each command runs once, in a fresh process, for two revisions checked out as git worktrees
(`--before`, the whole-tensor float64 version; `--after`, the streamed one), so other uncommitted
changes in the working tree play no part:
- `lib`: `vector_ops.stats(vector)` alone (no store);
- `cli`: `capvector vector stats <file>` as a user runs it (fresh CAPVECTOR_HOME: the file is imported
  into the store, hashed, and the rows registered).
Peak RSS and CPU time come from `wait4` on that process (Linux ru_maxrss). The file is read once,
untimed, before each run, so all find it in page cache. 2 cores shared with other jobs: the load
average is recorded.

Usage: .venv/bin/python benchmarks/bench_vector_stats.py [--mib 1024] [--before REV] [--after REV]
       [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
PY = sys.executable

LIB = (
    "from capvector.core.vectors.vector_ops import stats; import sys; rows = stats(sys.argv[1]); "
    "print(rows[0].l2)"
)


def write_vector(path: Path, mib: int) -> int:
    """One float32 tensor `w` of `mib` MiB, standard normal, written 16 MiB at a time."""
    n = mib * (1 << 20) // 4
    header = json.dumps({"w": {"dtype": "F32", "shape": [n], "data_offsets": [0, 4 * n]}}).encode()
    header += b" " * (-len(header) % 8)
    rng = np.random.default_rng(0)
    with open(path, "wb") as f:
        f.write(len(header).to_bytes(8, "little") + header)
        left = n
        while left:
            k = min(left, 4 << 20)
            f.write(rng.standard_normal(k, dtype=np.float32).tobytes())
            left -= k
    return n


def warm(path: Path) -> None:
    with open(path, "rb", buffering=0) as f:
        while f.read(64 << 20):
            pass


def measure(cmd: list[str], cwd: Path, env: dict[str, str]) -> dict:
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    out, err = proc.stdout.read().decode(), proc.stderr.read().decode()
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise RuntimeError(f"{cmd} exited {proc.returncode}: {err[-2000:]}")
    return {
        "wall_s": round(wall, 2),
        "cpu_s": round(usage.ru_utime + usage.ru_stime, 2),
        "peak_rss_mib": round(usage.ru_maxrss / 1024, 1),  # KiB on Linux
        "stdout_tail": out.strip().splitlines()[-1][:200] if out.strip() else "",
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--mib", type=int, default=1024)
    ap.add_argument("--before", default="5260c60~1")
    ap.add_argument("--after", default="5260c60")
    ap.add_argument("--work", type=Path, default=None)
    args = ap.parse_args()
    work = Path(args.work or tempfile.mkdtemp(prefix="bench_vector_stats_"))
    work.mkdir(parents=True, exist_ok=True)
    revs = {
        name: subprocess.run(
            ["git", "rev-parse", "--short", rev], cwd=ROOT, text=True, capture_output=True, check=True
        ).stdout.strip()
        for name, rev in (("before", args.before), ("after", args.after))
    }
    trees = {}
    try:
        for name, rev in revs.items():
            trees[name] = work / f"tree_{name}"
            subprocess.run(
                ["git", "worktree", "add", "--detach", "-f", str(trees[name]), rev],
                cwd=ROOT,
                check=True,
                capture_output=True,
            )
        vector = work / "vector.safetensors"
        t = time.perf_counter()
        n = write_vector(vector, args.mib)
        build_s = time.perf_counter() - t
        load_start = os.getloadavg()
        samples: dict[str, dict] = {}
        for name, tree in trees.items():
            env = {**os.environ, "PYTHONPATH": str(tree)}
            warm(vector)
            samples[f"{name}_lib"] = measure([PY, "-c", LIB, str(vector)], tree, env)
            home = work / f"home_{name}"
            shutil.rmtree(home, ignore_errors=True)
            env = {**env, "CAPVECTOR_HOME": str(home), "PREFECT_HOME": str(work / f"prefect_{name}")}
            warm(vector)
            samples[f"{name}_cli"] = measure(
                [PY, "-m", "capvector", "--home", str(home), "vector", "stats", str(vector), "--json"],
                tree,
                env,
            )
            shutil.rmtree(home, ignore_errors=True)
            print(name, samples[f"{name}_lib"], samples[f"{name}_cli"], flush=True)
        result = {
            "machine": {
                "python": platform.python_version(),
                "numpy": np.__version__,
                "cpus": os.cpu_count(),
                "load_at_start": list(load_start),
                "load_at_end": list(os.getloadavg()),
            },
            "vector": {
                "mib": args.mib,
                "elements": n,
                "dtype": "float32",
                "tensors": 1,
                "build_s": round(build_s, 1),
            },
            "revisions": revs,
            "samples": samples,
        }
    finally:
        for tree in trees.values():
            subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=ROOT, capture_output=True)
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    (RESULTS / "vector_stats.json").write_text(json.dumps(result, indent=2) + "\n")
    s = samples
    lines = [
        "# `vector stats` peak memory (bench_vector_stats.py)",
        "",
        f"One float32 tensor of {args.mib} MiB ({n:,} elements) in one file, vector only. Each command once, "
        f"in a fresh process, for `{revs['before']}` (whole tensors widened to float64) and "
        f"`{revs['after']}` "
        "(streamed in 4 MiB pieces). `cli`: `capvector vector stats <file> --json` with a fresh home (import "
        "into the store, hashing, registration included); `lib`: `vector_ops.stats` alone. Inputs in page "
        "cache; 2 cores shared with other jobs: load average "
        f"{load_start[0]:.1f} at the start, {result['machine']['load_at_end'][0]:.1f} at the end.",
        "",
        "| command | revision | wall s | CPU s | peak RSS MiB |",
        "|---|---|---|---|---|",
    ]
    for key, row in s.items():
        name, kind = key.split("_")
        lines.append(
            f"| {kind} | {name} ({revs[name]}) | {row['wall_s']} | {row['cpu_s']} | {row['peak_rss_mib']} |"
        )
    lines += [
        "",
        f"- **peak RSS of `capvector vector stats`: {s['before_cli']['peak_rss_mib']:.0f} MiB before, "
        f"{s['after_cli']['peak_rss_mib']:.0f} MiB after** (library call alone: "
        f"{s['before_lib']['peak_rss_mib']:.0f} → {s['after_lib']['peak_rss_mib']:.0f} MiB).",
        f"- ‖γ‖ printed by the two library runs: {s['before_lib']['stdout_tail']} / "
        f"{s['after_lib']['stdout_tail']}.",
        "",
    ]
    (RESULTS / "vector_stats.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
