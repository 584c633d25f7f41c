"""Benchmark: the streamed mean of K capability vectors against loading them all and averaging.

K = 8 float32 vectors of a ~50M-parameter checkpoint (a 14-layer transformer's shapes: 52M, 59 tensors,
~200 MiB each, 1.6 GiB in all), written once with distinct random values. Each command runs in a fresh
process, its peak RSS and CPU time from `wait4` (Linux ru_maxrss); the inputs are read once, untimed,
before each run, so all find them in page cache:
- `streamed`: `vector_ops.mean(paths, out)` (tensor by tensor, 4 MiB pieces of each input at a time,
  every input hashed while read, the output written atomically with its provenance metadata);
- `load_all`: the obvious alternative, `safetensors.torch.load_file` on every input, then per tensor
  `torch.stack([...]).mean(0)`, then `save_file`;
- `ties` (once, for its cost): `vector_ops.mean(paths, out, method="ties")`, density 0.2 (the
  threshold's radix selection reads each multi-piece float32 tensor twice more).
The two means alternate which goes first; ratios pair the runs of one repetition, the headline is
their median. The outputs are compared (normwise relative difference: torch sums in another order).
2 cores shared with other jobs: the load average is recorded.

Usage: .venv/bin/python benchmarks/bench_vector_mean.py [--k 8] [--reps 3] [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
PY = sys.executable

STREAMED = """
import sys
from capvector.core.vectors.vector_ops import mean
mean(sys.argv[2:], sys.argv[1], method="{method}")
"""
LOAD_ALL = """
import sys, torch
from safetensors.torch import load_file, save_file
vectors = [load_file(p) for p in sys.argv[2:]]
out = {k: torch.stack([v[k] for v in vectors]).mean(0) for k in vectors[0]}
save_file(out, sys.argv[1])
"""


def shapes(layers: int = 14, d: int = 512, vocab: int = 8192, mlp: int = 2048) -> dict[str, tuple]:
    out: dict[str, tuple] = {"embed.weight": (vocab, d)}
    for i in range(layers):
        p = f"blocks.{i}."
        out |= {
            p + "attn.qkv.weight": (3 * d, d),
            p + "attn.out.weight": (d, d),
            p + "mlp.up.weight": (mlp, d),
            p + "mlp.down.weight": (d, mlp),
        }
    return out | {"norm.weight": (d,), "head.weight": (vocab, d)}


def write_vectors(work: Path, k: int) -> list[Path]:
    from safetensors.numpy import save_file

    rng = np.random.default_rng(0)
    paths = []
    for i in range(k):
        path = work / f"gamma_{i}.safetensors"
        save_file({n: rng.standard_normal(s, dtype=np.float32) for n, s in shapes().items()}, str(path))
        paths.append(path)
    return paths


def warm(paths: list[Path]) -> None:
    for path in paths:
        with open(path, "rb", buffering=0) as f:
            while f.read(64 << 20):
                pass


def measure(code: str, out: Path, inputs: list[Path]) -> dict:
    out.unlink(missing_ok=True)
    warm(inputs)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    start = time.perf_counter()
    proc = subprocess.Popen(
        [PY, "-c", code, str(out), *map(str, inputs)], cwd=ROOT, env=env, stderr=subprocess.PIPE
    )
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    err = proc.stderr.read().decode()
    if os.waitstatus_to_exitcode(status):
        raise RuntimeError(f"exited {os.waitstatus_to_exitcode(status)}: {err[-2000:]}")
    return {
        "wall_s": round(wall, 2),
        "cpu_s": round(usage.ru_utime + usage.ru_stime, 2),
        "peak_rss_mib": round(usage.ru_maxrss / 1024, 1),  # KiB on Linux
        "load_1m": round(os.getloadavg()[0], 2),
    }


def difference(a: Path, b: Path) -> float:
    """‖a − b‖ / ‖b‖ over all tensors, one tensor at a time."""
    from safetensors import safe_open

    num = den = 0.0
    with safe_open(str(a), "np") as fa, safe_open(str(b), "np") as fb:
        for name in fb.keys():
            x, y = fa.get_tensor(name).astype(np.float64), fb.get_tensor(name).astype(np.float64)
            num += float(((x - y) ** 2).sum())
            den += float((y**2).sum())
    return math.sqrt(num / den)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--k", type=int, default=8)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--work", type=Path, default=None)
    args = ap.parse_args()
    work = Path(args.work or tempfile.mkdtemp(prefix="bench_vector_mean_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        t = time.perf_counter()
        inputs = write_vectors(work, args.k)
        build_s = time.perf_counter() - t
        params = sum(math.prod(s) for s in shapes().values())
        load_start = os.getloadavg()
        samples: dict[str, list[dict]] = {"streamed": [], "load_all": []}
        codes = {"streamed": STREAMED.format(method="mean"), "load_all": LOAD_ALL}
        for rep in range(args.reps):
            order = ["streamed", "load_all"] if rep % 2 == 0 else ["load_all", "streamed"]
            for name in order:
                samples[name].append(measure(codes[name], work / f"{name}.safetensors", inputs))
                print(rep, name, samples[name][-1], flush=True)
        ties = measure(STREAMED.format(method="ties"), work / "ties.safetensors", inputs)
        print("ties", ties, flush=True)
        diff = difference(work / "streamed.safetensors", work / "load_all.safetensors")
        load_end = os.getloadavg()
    finally:
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)

    pairs = list(zip(samples["streamed"], samples["load_all"], strict=True))
    wall_ratio = statistics.median(s["wall_s"] / a["wall_s"] for s, a in pairs)
    rss_ratio = statistics.median(s["peak_rss_mib"] / a["peak_rss_mib"] for s, a in pairs)
    cpu_ratio = statistics.median(s["cpu_s"] / a["cpu_s"] for s, a in pairs)
    med = {n: {f: statistics.median(r[f] for r in rows) for f in rows[0]} for n, rows in samples.items()}
    result = {
        "machine": {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "cpus": os.cpu_count(),
            "load_at_start": list(load_start),
            "load_at_end": list(load_end),
        },
        "inputs": {
            "k": args.k,
            "params_per_vector": params,
            "tensors": len(shapes()),
            "mib_per_vector": round(params * 4 / 2**20, 1),
            "dtype": "float32",
            "build_s": round(build_s, 1),
        },
        "samples": samples,
        "ties": ties,
        "median": med,
        "ratios": {"wall": wall_ratio, "peak_rss": rss_ratio, "cpu": cpu_ratio},
        "normwise_relative_difference": diff,
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "vector_mean.json").write_text(json.dumps(result, indent=2) + "\n")
    mib = result["inputs"]["mib_per_vector"]
    lines = [
        "# Streamed mean of K vectors (bench_vector_mean.py)",
        "",
        f"K = {args.k} float32 vectors of {params / 1e6:.1f}M parameters ({len(shapes())} tensors, "
        f"{mib:.0f} MiB each, {args.k * mib / 1024:.2f} GiB in all), in page cache. `streamed`: "
        "`vector_ops.mean` (4 MiB pieces of each input at a time, inputs hashed while read, provenance "
        "metadata); `load_all`: `safetensors.torch.load_file` on every input, `torch.stack(...).mean(0)` "
        "per tensor, `save_file`. Each run a fresh process (peak RSS from `wait4`), the two alternating "
        f"which goes first, {args.reps} repetitions; ratios pair the runs of one repetition, headline = "
        f"median. 2 cores shared with other jobs: load average {load_start[0]:.1f} at the start, "
        f"{load_end[0]:.1f} at the end.",
        "",
        "| command | median wall s | median CPU s | median peak RSS MiB |",
        "|---|---|---|---|",
    ]
    for name, m in med.items():
        lines.append(f"| {name} | {m['wall_s']:.2f} | {m['cpu_s']:.2f} | {m['peak_rss_mib']:.0f} |")
    lines.append(f"| ties (once) | {ties['wall_s']:.2f} | {ties['cpu_s']:.2f} | {ties['peak_rss_mib']:.0f} |")
    per_rep = ", ".join(f"{s['wall_s'] / a['wall_s']:.2f}" for s, a in pairs)
    lines += [
        "",
        f"- **wall time, streamed / load_all: {wall_ratio:.2f}×** (per repetition {per_rep}; CPU time "
        f"{cpu_ratio:.2f}×).",
        f"- **peak RSS, streamed / load_all: {rss_ratio:.3f}×** ({med['streamed']['peak_rss_mib']:.0f} MiB "
        f"vs {med['load_all']['peak_rss_mib']:.0f} MiB; the inputs alone are {args.k * mib:.0f} MiB).",
        f"- outputs: normwise relative difference {diff:.1e}"
        + (" (the same values)." if diff == 0 else " (torch's mean sums in another order)."),
        f"- TIES (density 0.2) on the same inputs: {ties['wall_s']:.2f} s, peak RSS "
        f"{ties['peak_rss_mib']:.0f} MiB (each multi-piece float32 tensor read three times: two radix "
        "passes for its threshold, then the merge).",
        "",
    ]
    (RESULTS / "vector_mean.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
