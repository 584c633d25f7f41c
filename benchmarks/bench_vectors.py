"""Benchmark (a): streaming extract + merge on a synthetic sharded bfloat16 checkpoint (≥ 2 GiB).

Compares, on the same files and in one run, with repetitions interleaved:
- ours: `extract(θ_ao, θ_ft) -> γ` then `merge(θ_pt, [(γ, α)]) -> θ_meta` (two passes, two outputs);
- mergekit 0.1.5 `task_arithmetic` (one pass: base θ_ft, θ_pt weight 1, θ_ao weight α, normalize false,
  dtype float32, out_dtype bfloat16 — the same float32 arithmetic as ours), installed by this script in
  its own venv `benchmarks/_work/mergekit-venv`. `mergekit-pytorch` loads one file per model (its
  `ShardedTensorIndex.from_file` does not read a shard index), so it gets single-file copies of the same
  tensors;
- the I/O floor of each of our passes: read both inputs, write one output, no arithmetic and no hashing.
Each command runs in its own process under /usr/bin/time (wall time, peak RSS). Files are in page cache
for every command alike (each input is read by an earlier command first). Targets: faster than
mergekit, within 2x the floor, peak RSS under 2x the largest tensor plus the interpreter.

Usage: .venv/bin/python benchmarks/bench_vectors.py [--reps 2] [--keep]
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from capvector_core.safetensors_io import Checkpoint, ShardedWriter  # noqa: E402

WORK = ROOT / "benchmarks" / "_work"  # --work moves it: other benchmarks wipe benchmarks/_work when done
DATA = WORK / "vectors"
VENV = WORK / "mergekit-venv"
RESULTS = ROOT / "benchmarks" / "results"
ALPHA = 1.1
PY = sys.executable


def layout() -> dict[str, tuple[torch.dtype, tuple[int, ...]]]:
    """30 × 64 MiB + one 128 MiB bfloat16 matrix + small biases and an int64 counter: 2.0 GiB."""
    specs: dict[str, tuple[torch.dtype, tuple[int, ...]]] = {"embed.weight": (torch.bfloat16, (8192, 8192))}
    for i in range(30):
        specs[f"layers.{i}.weight"] = (torch.bfloat16, (4096, 8192))
        specs[f"layers.{i}.bias"] = (torch.bfloat16, (4096,))
    specs["step"] = (torch.int64, ())
    return specs


def build() -> None:
    specs = layout()
    for name, seed in (("pt", 0), ("ft", 1), ("ao", 2)):
        out = DATA / name
        if out.exists():
            continue
        g = torch.Generator().manual_seed(seed)
        with ShardedWriter(out, specs, max_shard_bytes=1 << 30) as w:
            for n in w.order:
                dtype, shape = specs[n]
                w.write(
                    n, torch.tensor(7) if dtype == torch.int64 else torch.randn(shape, generator=g).to(dtype)
                )


def consolidate() -> None:
    """Single-file copies for mergekit-pytorch, whose loader takes one file per model, not a shard index."""
    for name in ("pt", "ft", "ao"):
        out = DATA / f"{name}.safetensors"
        if out.exists():
            continue
        src = Checkpoint(DATA / name)
        with ShardedWriter(out, {n: (s.torch_dtype, s.shape) for n, s in src.specs.items()}) as w:
            for n in w.order:
                w.write(n, src.get(n))


def ensure_mergekit() -> str | None:
    """Install mergekit in its own venv; return an error text instead of raising."""
    exe = VENV / "bin" / "mergekit-pytorch"
    if exe.exists():
        return None
    try:
        subprocess.run([sys.executable, "-m", "venv", str(VENV)], check=True)
        pip = [str(VENV / "bin" / "pip"), "install", "-q"]
        subprocess.run([*pip, "torch==2.13.0"], check=True, timeout=1200)
        subprocess.run([*pip, "mergekit"], check=True, timeout=1200)
    except (subprocess.SubprocessError, OSError) as e:
        return f"mergekit install failed: {e!r}"
    return None


def timed(cmd: list[str]) -> dict:
    """Wall seconds and peak RSS (MiB) of `cmd` in a fresh process."""
    stats = WORK / "time.txt"
    t = time.perf_counter()
    proc = subprocess.run(
        ["/usr/bin/time", "-f", "%M", "-o", str(stats), *cmd], capture_output=True, text=True
    )
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise RuntimeError(f"{cmd[:3]} failed:\n{proc.stderr[-3000:]}")
    return {"wall_s": wall, "peak_rss_mib": int(stats.read_text().split()[-1]) / 1024}


OURS_EXTRACT = "from capvector_core.vector_ops import extract; extract({a!r}, {b!r}, {out!r}, overwrite=True)"
OURS_MERGE = (
    "from capvector_core.vector_ops import merge; merge({a!r}, [({b!r}, {alpha})], {out!r}, overwrite=True)"
)
FLOOR = """
from capvector_core.safetensors_io import Checkpoint, ShardedWriter
a, b = Checkpoint({a!r}), Checkpoint({b!r})
specs = {{n: (s.torch_dtype, s.shape) for n, s in a.specs.items()}}
with ShardedWriter({out!r}, specs, overwrite=True) as w:
    for n in w.order:
        b.read_raw(n)
        w.write(n, a.get(n))
"""
INTERPRETER = "import torch, capvector_core.vector_ops"


def py(code: str, **kw) -> list[str]:
    return [PY, "-c", f"import sys; sys.path.insert(0, {str(ROOT)!r})\n" + code.format(**kw)]


def mergekit_cmd(out: Path) -> list[str]:
    config = {
        "merge_method": "task_arithmetic",
        "base_model": str(DATA / "ft.safetensors"),
        "models": [
            {"model": str(DATA / "pt.safetensors"), "parameters": {"weight": 1.0}},
            {"model": str(DATA / "ao.safetensors"), "parameters": {"weight": ALPHA}},
        ],
        "parameters": {"normalize": False},
        "dtype": "float32",
        "out_dtype": "bfloat16",
    }
    path = WORK / "mergekit.yaml"
    path.write_text(json.dumps(config))  # JSON is YAML
    return [str(VENV / "bin" / "mergekit-pytorch"), str(path), str(out)]


def compare_outputs(ours: Path, theirs: Path) -> dict:
    """Normwise relative difference ‖ours − mergekit‖ / ‖mergekit‖ on a few tensors."""
    a, b = Checkpoint(ours), Checkpoint(theirs)
    worst = 0.0
    for n in ("layers.0.weight", "embed.weight", "layers.29.bias"):
        x, y = a.get(n).float(), b.get(n).float()
        worst = max(worst, float((x - y).norm() / y.norm()))
    return {"max_rel_diff_sample": worst, "same_keys": set(a.keys()) == set(b.keys())}


def main() -> None:
    global WORK, DATA, VENV
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--keep", action="store_true", help="keep the synthetic checkpoints")
    ap.add_argument("--work", type=Path, default=WORK, help="scratch directory (checkpoints, mergekit venv)")
    args = ap.parse_args()
    WORK, DATA, VENV = args.work, args.work / "vectors", args.work / "mergekit-venv"
    DATA.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    build()
    build_s = time.perf_counter() - t
    mk_error = ensure_mergekit()
    ckpt = Checkpoint(DATA / "pt")
    gamma, meta, floor_out, mk_out = (DATA / n for n in ("gamma", "meta", "floor", "mergekit"))
    runs = {
        "ours_extract": py(OURS_EXTRACT, a=str(DATA / "ao"), b=str(DATA / "ft"), out=str(gamma)),
        "ours_merge": py(OURS_MERGE, a=str(DATA / "pt"), b=str(gamma), alpha=ALPHA, out=str(meta)),
        "floor_extract": py(FLOOR, a=str(DATA / "ao"), b=str(DATA / "ft"), out=str(floor_out)),
        "floor_merge": py(FLOOR, a=str(DATA / "pt"), b=str(gamma), out=str(floor_out)),
        "interpreter": py(INTERPRETER),
    }
    if mk_error is None:
        consolidate()
        runs["mergekit"] = mergekit_cmd(mk_out)
    samples: dict[str, list[dict]] = {k: [] for k in runs}
    for rep in range(args.reps):
        for name, cmd in runs.items():
            if name == "mergekit":
                shutil.rmtree(mk_out, ignore_errors=True)
            samples[name].append(timed(cmd))
            print(f"rep {rep} {name}: {samples[name][-1]}", flush=True)
    best = {k: {m: min(s[m] for s in v) for m in ("wall_s", "peak_rss_mib")} for k, v in samples.items()}
    ours = best["ours_extract"]["wall_s"] + best["ours_merge"]["wall_s"]
    floor = best["floor_extract"]["wall_s"] + best["floor_merge"]["wall_s"]
    largest = ckpt.largest_tensor_nbytes / 2**20
    rss_limit = 2 * largest + best["interpreter"]["peak_rss_mib"]
    ours_rss = max(best["ours_extract"]["peak_rss_mib"], best["ours_merge"]["peak_rss_mib"])
    result = {
        "checkpoint": {
            "bytes": ckpt.nbytes,
            "tensors": len(ckpt),
            "shards": len(ckpt.files),
            "largest_tensor_mib": largest,
            "dtype": "bfloat16",
        },
        "build_s": build_s,
        "reps": args.reps,
        "samples": samples,
        "best": best,
        "ours_total_s": ours,
        "floor_total_s": floor,
        "ratio_to_floor": ours / floor,
        "rss_limit_mib": rss_limit,
        "ours_peak_rss_mib": ours_rss,
        "targets": {
            "within_2x_floor": ours / floor <= 2.0,
            "rss_under_limit": ours_rss <= rss_limit,
        },
        "mergekit": {"error": mk_error, "config": "task_arithmetic, dtype float32, out_dtype bfloat16"},
        "machine": {
            "python": platform.python_version(),
            "torch": torch.__version__,
            "cpus": torch.get_num_threads(),
        },
    }
    if mk_error is None:
        result["mergekit"]["wall_s"] = best["mergekit"]["wall_s"]
        result["mergekit"]["peak_rss_mib"] = best["mergekit"]["peak_rss_mib"]
        result["targets"]["faster_than_mergekit"] = ours < best["mergekit"]["wall_s"]
        result["mergekit"]["agreement"] = compare_outputs(meta, mk_out)
    write_results(result)
    if not args.keep:
        shutil.rmtree(DATA, ignore_errors=True)


def write_results(r: dict) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "vectors.json").write_text(json.dumps(r, indent=2))
    b = r["best"]
    c = r["checkpoint"]
    lines = [
        "# Vector ops benchmark (bench_vectors.py)",
        "",
        f"Synthetic sharded bfloat16 checkpoint: {c['bytes'] / 2**30:.2f} GiB, {c['tensors']} tensors, "
        f"{c['shards']} shards, largest tensor {c['largest_tensor_mib']:.0f} MiB; three of them "
        f"(θ_pt, θ_ft, θ_ao). Best of {r['reps']} interleaved repetitions, each command in a fresh "
        "process, inputs in page cache.",
        "",
        "| command | wall s | peak RSS MiB |",
        "|---|---|---|",
    ]
    for k, v in b.items():
        lines.append(f"| {k} | {v['wall_s']:.2f} | {v['peak_rss_mib']:.0f} |")
    lines += [
        "",
        f"- ours (extract + merge, two passes, input hashing included): **{r['ours_total_s']:.2f} s**; "
        f"I/O floor of the same two passes: {r['floor_total_s']:.2f} s; ratio **{r['ratio_to_floor']:.2f}x** "
        f"(target ≤ 2x: {'met' if r['targets']['within_2x_floor'] else 'NOT met'}).",
        f"- peak RSS {r['ours_peak_rss_mib']:.0f} MiB vs limit 2 × largest tensor + interpreter = "
        f"{r['rss_limit_mib']:.0f} MiB ({'met' if r['targets']['rss_under_limit'] else 'NOT met'}).",
    ]
    mk = r["mergekit"]
    if mk["error"]:
        lines.append(f"- mergekit: not measured ({mk['error']}).")
    else:
        lines.append(
            f"- mergekit {mk['config']} (one pass, one output): **{mk['wall_s']:.2f} s**, "
            f"peak RSS {mk['peak_rss_mib']:.0f} MiB; faster than mergekit: "
            f"{'yes' if r['targets']['faster_than_mergekit'] else 'NO'}; outputs agree to "
            f"{mk['agreement']['max_rel_diff_sample']:.2g} (normwise relative, sampled tensors; our two-pass "
            "path rounds γ to bfloat16 before merging, mergekit does not)."
        )
    (RESULTS / "vectors.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
