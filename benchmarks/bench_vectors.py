"""Benchmark (a): `capvector vector extract` + `capvector vector merge` against mergekit, at two sizes.

Cases: a 256 MiB float32 checkpoint (one file) and a 2 GiB bfloat16 one (3 shards); three of each
(θ_pt, θ_ft, θ_ao). For each case, every repetition runs, interleaved, each command in a fresh process
under /usr/bin/time (wall, CPU, peak RSS):
- ours, as a user runs it: `capvector vector extract θ_ao θ_ft -o γ`, then `capvector vector merge
  θ_pt --vector γ --alpha 1.1 -o θ_meta`, with a fresh CAPVECTOR_HOME and PREFECT_HOME in a temp dir
  (so every input is imported into the store, every output registered and placed at `-o`);
- mergekit 0.1.x `task_arithmetic` (one pass: base θ_ft, θ_pt weight 1, θ_ao weight α, normalize
  false, dtype float32, out_dtype the checkpoint's — the same float32 arithmetic as ours), installed by
  this script in its own venv. `mergekit-pytorch` loads one file per model (no shard index), so the
  sharded case gives it single-file copies of the same tensors;
- the cost of verified reads (issue 15): the same two commands with the artifact ids as inputs
  (stored inputs, hashed while they are read and checked against their ids), and again with that
  check patched out (`UNVERIFIED`: a benchmark-only patch, no switch of the CLI);
- the library calls alone (`vector_ops.extract`/`merge`, no store) and their I/O floor (read both
  inputs, write one output: no arithmetic, no hashing).
Each command's inputs are read (untimed) just before it, so that all find them in page cache. Ratios
compare runs of one repetition (same load); the headline is their median. The machine has 2 cores
shared with other jobs: the load average is recorded with every sample.

Usage: .venv/bin/python benchmarks/bench_vectors.py [--reps 3] [--cases f32_256m,bf16_2g] [--work DIR]
       [--before REV] [--keep]   (--work outside benchmarks/_work: other benchmarks wipe it)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from capvector.core.vectors.safetensors_io import Checkpoint, ShardedWriter  # noqa: E402

# --work moves it: other benchmarks wipe benchmarks/_work when done (and the mergekit venv with it)
WORK = ROOT / "benchmarks" / "_work"
RESULTS = ROOT / "benchmarks" / "results"
ALPHA = 1.1
PY = sys.executable
CONSOLE = Path(PY).parent / "capvector"  # the console script a user runs
CAPVECTOR = [str(CONSOLE)] if CONSOLE.exists() else [PY, "-m", "capvector"]
Specs = dict[str, tuple[torch.dtype, tuple[int, ...]]]


def layout_f32_256m() -> Specs:
    """One 32 MiB and 14 × 16 MiB float32 matrices + biases and an int64 counter: 256 MiB."""
    specs: Specs = {"embed.weight": (torch.float32, (2048, 4096))}
    for i in range(14):
        specs[f"layers.{i}.weight"] = (torch.float32, (1024, 4096))
        specs[f"layers.{i}.bias"] = (torch.float32, (1024,))
    specs["step"] = (torch.int64, ())
    return specs


def layout_bf16_2g() -> Specs:
    """30 × 64 MiB + one 128 MiB bfloat16 matrix + small biases and an int64 counter: 2.0 GiB."""
    specs: Specs = {"embed.weight": (torch.bfloat16, (8192, 8192))}
    for i in range(30):
        specs[f"layers.{i}.weight"] = (torch.bfloat16, (4096, 8192))
        specs[f"layers.{i}.bias"] = (torch.bfloat16, (4096,))
    specs["step"] = (torch.int64, ())
    return specs


CASES = {
    "f32_256m": dict(
        layout=layout_f32_256m, sharded=False, dtype="float32", label="256 MiB float32, one file"
    ),
    "bf16_2g": dict(layout=layout_bf16_2g, sharded=True, dtype="bfloat16", label="2 GiB bfloat16, 3 shards"),
}


def build(data: Path, specs: Specs, sharded: bool) -> dict[str, Path]:
    """θ_pt, θ_ft, θ_ao (random, seeds 0-2): sharded folders or single files."""
    paths = {}
    for name, seed in (("pt", 0), ("ft", 1), ("ao", 2)):
        out = data / (name if sharded else f"{name}.safetensors")
        paths[name] = out
        if out.exists():
            continue
        g = torch.Generator().manual_seed(seed)
        with ShardedWriter(out, specs, max_shard_bytes=1 << 30) as w:
            for n in w.order:
                dtype, shape = specs[n]
                w.write(
                    n, torch.tensor(7) if dtype == torch.int64 else torch.randn(shape, generator=g).to(dtype)
                )
    return paths


def single_files(data: Path, paths: dict[str, Path]) -> dict[str, Path]:
    """Single-file copies for mergekit-pytorch, whose loader takes one file per model, not a shard index."""
    out = {}
    for name, src_path in paths.items():
        if src_path.is_file():
            out[name] = src_path
            continue
        out[name] = dst = data / f"{name}.safetensors"
        if dst.exists():
            continue
        src = Checkpoint(src_path)
        with ShardedWriter(dst, {n: (s.torch_dtype, s.shape) for n, s in src.specs.items()}) as w:
            for n in w.order:
                w.write(n, src.get(n))
    return out


def ensure_mergekit(venv: Path) -> str | None:
    """Install mergekit in its own venv; return an error text instead of raising."""
    if (venv / "bin" / "mergekit-pytorch").exists():
        return None
    try:
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
        pip = [str(venv / "bin" / "pip"), "install", "-q"]
        subprocess.run([*pip, "torch==2.13.0"], check=True, timeout=1200)
        subprocess.run([*pip, "mergekit"], check=True, timeout=1200)
    except (subprocess.SubprocessError, OSError) as e:
        return f"mergekit install failed: {e!r}"
    return None


def timed(cmd: list[str], env: dict[str, str] | None = None, cwd: Path = ROOT) -> dict:
    """Wall and CPU seconds and peak RSS (MiB) of `cmd` in a fresh process, with the load average."""
    with tempfile.NamedTemporaryFile("r", suffix=".time") as stats:
        t = time.perf_counter()
        proc = subprocess.run(
            ["/usr/bin/time", "-f", "%M %U %S", "-o", stats.name, *cmd],
            capture_output=True,
            text=True,
            cwd=cwd,
            env={**os.environ, **(env or {})},
        )
        wall = time.perf_counter() - t
        if proc.returncode != 0:
            raise RuntimeError(f"{cmd[:4]} failed:\n{proc.stderr[-3000:]}")
        rss_kib, user, sys_ = stats.read().split()[-3:]
    return {
        "wall_s": wall,
        "cpu_s": float(user) + float(sys_),
        "peak_rss_mib": int(rss_kib) / 1024,
        "load_1m": os.getloadavg()[0],
    }


LIB_EXTRACT = (
    "from capvector.core.vectors.vector_ops import extract; "
    "extract({a!r}, {b!r}, {out!r}, overwrite=True)"
)
LIB_MERGE = (
    "from capvector.core.vectors.vector_ops import merge; "
    "merge({a!r}, [({b!r}, {alpha})], {out!r}, overwrite=True)"
)
FLOOR = """
from capvector.core.vectors.safetensors_io import STORAGE, Checkpoint, ShardedWriter
a, b = Checkpoint({a!r}), Checkpoint({b!r})
specs = {{n: (s.dtype, s.shape) for n, s in a.specs.items()}}
with ShardedWriter({out!r}, specs, overwrite=True) as w:
    for n in w.order:
        b.read_bytes(n)
        w.write_chunks(n, [a.read_bytes(n).view(STORAGE[a.specs[n].dtype])])
"""
# The CLI with stored inputs trusted instead of checked: they are read without hashing, and their
# recorded digests stand in for the hashes (benchmark only: how much the verified read costs).
UNVERIFIED = """
from capvector.artifacts import store
from capvector.core.vectors import vector_ops
from capvector.flows.cli.main import main

known = {}
stream_path = store.ArtifactStore.stream_path

def trusting_stream_path(self, ref):
    path, record = stream_path(self, ref)
    base = path.parent if record.layout == "file" else path
    known.update({base / f.path: f.sha256 for f in record.files})
    return path, record

class Unhashed(vector_ops._HashingReader):
    def chunks(self, name, bounds):
        dtype = vector_ops.STORAGE[self.ckpt.specs[name].dtype]
        for b, e in bounds:
            yield self.ckpt.read_bytes(name, b, e).view(dtype)

    def file_digests(self):
        return {f: known[f] for f in self.ckpt.files}

store.ArtifactStore.stream_path = trusting_stream_path
store.ArtifactStore.check_read = lambda self, record, path, hashes: {f.path: f.sha256 for f in record.files}
vector_ops._HashingReader = Unhashed
main()
"""


def py(code: str, **kw) -> list[str]:
    return [PY, "-c", f"import sys; sys.path.insert(0, {str(ROOT)!r})\n" + code.format(**kw)]


def unverified(*args: str) -> list[str]:
    head = f"import sys; sys.path.insert(0, {str(ROOT)!r}); sys.argv = ['capvector', *{args!r}]\n"
    return [PY, "-c", head + UNVERIFIED]


def mergekit_cmd(work: Path, venv: Path, files: dict[str, Path], dtype: str, out: Path) -> list[str]:
    config = {
        "merge_method": "task_arithmetic",
        "base_model": str(files["ft"]),
        "models": [
            {"model": str(files["pt"]), "parameters": {"weight": 1.0}},
            {"model": str(files["ao"]), "parameters": {"weight": ALPHA}},
        ],
        "parameters": {"normalize": False},
        "dtype": "float32",
        "out_dtype": dtype,
    }
    path = work / f"mergekit-{dtype}.yaml"
    path.write_text(json.dumps(config))  # JSON is YAML
    return [str(venv / "bin" / "mergekit-pytorch"), str(path), str(out)]


def compare_outputs(ours: Path, theirs: Path, names: list[str]) -> dict:
    """Normwise relative difference ‖ours − mergekit‖ / ‖mergekit‖ on a few tensors."""
    a, b = Checkpoint(ours), Checkpoint(theirs)
    worst = 0.0
    for n in names:
        x, y = a.get(n).float(), b.get(n).float()
        worst = max(worst, float((x - y).norm() / y.norm()))
    return {"max_rel_diff_sample": worst, "same_keys": set(a.keys()) == set(b.keys())}


def artifact_ids(home: Path) -> dict[str, str]:
    """name -> id of what a home holds (the CLI's imports are named after the user's files)."""
    from capvector.artifacts.store import ArtifactStore

    store = ArtifactStore(home / "store", cache_dir=home / "cache")
    return {r.name: r.id for r in store.iter_records()}


def warm(*paths: Path | str) -> None:
    """Read files once, untimed: every command then finds its inputs in page cache alike."""
    for path in map(Path, paths):
        for f in [path] if path.is_file() else sorted(x for x in path.rglob("*") if x.is_file()):
            with open(f, "rb", buffering=0) as fh:
                while fh.read(8 << 20):
                    pass


def checkout(rev: str, work: Path) -> Path:
    """The source tree as of `rev` (git archive: the repository is not touched), for `--before`."""
    dst = work / f"before-{rev}"
    if not dst.exists():
        dst.mkdir()
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev], check=True, capture_output=True)
        subprocess.run(["tar", "-x", "-C", str(dst)], input=archive.stdout, check=True)
    return dst


def run_case(
    key: str, work: Path, venv: Path, reps: int, mk_error: str | None, before: Path | None = None
) -> dict:
    case = CASES[key]
    data = work / key
    data.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    paths = build(data, case["layout"](), case["sharded"])
    files = single_files(data, paths) if mk_error is None else {}
    build_s = time.perf_counter() - t
    ckpt = Checkpoint(paths["pt"])
    ext = "" if case["sharded"] else ".safetensors"
    gamma, meta, lib_out, floor_out, mk_out = (
        data / f"{n}{ext}" for n in ("gamma", "meta", "lib", "floor", "mergekit")
    )
    samples: dict[str, list[dict]] = {}

    def sample(
        name: str, cmd: list[str], env: dict[str, str] | None = None, cwd: Path = ROOT, inputs=()
    ) -> None:
        warm(*inputs)
        samples.setdefault(name, []).append(timed(cmd, env, cwd))
        print(f"{key} {name}: {samples[name][-1]}", flush=True)

    for rep in range(reps):
        with tempfile.TemporaryDirectory(dir=work, prefix="home-") as tmp:
            home, env = Path(tmp) / "home", {"CAPVECTOR_HOME": str(Path(tmp) / "home")}
            env["PREFECT_HOME"] = str(Path(tmp) / "prefect")
            for p in (gamma, meta):
                shutil.rmtree(p) if p.is_dir() else p.unlink(missing_ok=True)
            a, f, p = (str(paths[n]) for n in ("ao", "ft", "pt"))
            sample(
                "ours_extract", [*CAPVECTOR, "vector", "extract", a, f, "-o", str(gamma)], env, inputs=(a, f)
            )
            merge = [
                *CAPVECTOR,
                "vector",
                "merge",
                p,
                "--vector",
                str(gamma),
                "--alpha",
                str(ALPHA),
                "-o",
                str(meta),
            ]
            sample("ours_merge", merge, env, inputs=(p, gamma))
            if mk_error is None:
                shutil.rmtree(mk_out, ignore_errors=True)
                mk_cmd = mergekit_cmd(work, venv, files, case["dtype"], mk_out)
                sample("mergekit", mk_cmd, inputs=files.values())
            if before is not None:  # the same two commands as of an older commit, in a home of their own
                old = {"CAPVECTOR_HOME": str(Path(tmp) / "before-home"), "PREFECT_HOME": env["PREFECT_HOME"]}
                g_old, m_old = (Path(tmp) / f"before-{n}{ext}" for n in ("gamma", "meta"))
                cli = [PY, "-m", "capvector", "vector"]
                sample("before_extract", [*cli, "extract", a, f, "-o", str(g_old)], old, before, (a, f))
                merge = [*cli, "merge", p, "--vector", str(g_old), "--alpha", str(ALPHA), "-o", str(m_old)]
                sample("before_merge", merge, old, before, (p, g_old))
            ids = artifact_ids(home)
            (a_id, f_id, p_id), g_id = (ids[Path(x).name] for x in (a, f, p)), ids[gamma.stem]
            obj = {i: home / "store" / "objects" / i[:2] / i for i in (a_id, f_id, p_id, g_id)}
            variants = [("verified", lambda *x: [*CAPVECTOR, *x]), ("unverified", unverified)]
            for variant, cli in variants if rep % 2 == 0 else variants[::-1]:  # neither always goes first
                g_out, m_out = (Path(tmp) / f"{variant}-{n}{ext}" for n in ("gamma", "meta"))
                extract = ("vector", "extract", a_id, f_id, "-o", str(g_out))
                sample(f"ids_extract_{variant}", cli(*extract), env, inputs=(obj[a_id], obj[f_id]))
                merge = ("vector", "merge", p_id, "--vector", g_id, "--alpha", str(ALPHA), "-o", str(m_out))
                sample(f"ids_merge_{variant}", cli(*merge), env, inputs=(obj[p_id], obj[g_id]))
        lib_in = {"a": str(paths["ao"]), "b": str(paths["ft"])}
        sample("lib_extract", py(LIB_EXTRACT, **lib_in, out=str(lib_out)), inputs=lib_in.values())
        lib_in = {"a": str(paths["pt"]), "b": str(lib_out)}
        sample(
            "lib_merge", py(LIB_MERGE, **lib_in, alpha=ALPHA, out=str(lib_out) + "m"), inputs=lib_in.values()
        )
        lib_in = {"a": str(paths["ao"]), "b": str(paths["ft"])}
        sample("floor_extract", py(FLOOR, **lib_in, out=str(floor_out)), inputs=lib_in.values())
        lib_in = {"a": str(paths["pt"]), "b": str(lib_out)}
        sample("floor_merge", py(FLOOR, **lib_in, out=str(floor_out)), inputs=lib_in.values())
    return summarize(key, case, ckpt, build_s, reps, samples, meta, mk_out, mk_error)


def summarize(key, case, ckpt, build_s, reps, samples, meta, mk_out, mk_error) -> dict:
    def per_rep(*names: str, metric: str = "wall_s") -> list[float]:
        return [sum(samples[n][i][metric] for n in names) for i in range(reps)]

    best = {
        k: {m: min(s[m] for s in v) for m in ("wall_s", "cpu_s", "peak_rss_mib")} for k, v in samples.items()
    }
    ours = per_rep("ours_extract", "ours_merge")
    checked, trusted = (
        ("ids_extract_verified", "ids_merge_verified"),
        ("ids_extract_unverified", "ids_merge_unverified"),
    )
    verified, unverified_s = per_rep(*checked), per_rep(*trusted)
    verified_cpu, unverified_cpu = per_rep(*checked, metric="cpu_s"), per_rep(*trusted, metric="cpu_s")
    lib, floor = per_rep("lib_extract", "lib_merge"), per_rep("floor_extract", "floor_merge")
    ours_rss = max(best["ours_extract"]["peak_rss_mib"], best["ours_merge"]["peak_rss_mib"])
    loads = [s["load_1m"] for v in samples.values() for s in v]
    result = {
        "label": case["label"],
        "checkpoint": {
            "bytes": ckpt.nbytes,
            "tensors": len(ckpt),
            "files": len(ckpt.files),
            "largest_tensor_mib": ckpt.largest_tensor_nbytes / 2**20,
            "dtype": case["dtype"],
        },
        "build_s": build_s,
        "reps": reps,
        "samples": samples,
        "best": best,
        "load_1m": {"min": min(loads), "median": statistics.median(loads), "max": max(loads)},
        "ours_cli_s": {"per_rep": ours, "median": statistics.median(ours), "best": min(ours)},
        "ours_peak_rss_mib": ours_rss,
        "verification": {
            "verified_s": verified,
            "unverified_s": unverified_s,
            "cost_median": statistics.median(v / u - 1 for v, u in zip(verified, unverified_s, strict=True)),
            "verified_cpu_s": verified_cpu,
            "unverified_cpu_s": unverified_cpu,
            "cpu_cost_median": statistics.median(
                v / u - 1 for v, u in zip(verified_cpu, unverified_cpu, strict=True)
            ),
        },
        "library": {
            "lib_s": lib,
            "floor_s": floor,
            "ratio_to_floor_median": statistics.median(a / b for a, b in zip(lib, floor, strict=True)),
        },
        "mergekit": {
            "error": mk_error,
            "config": f"task_arithmetic, dtype float32, out_dtype {case['dtype']}",
        },
    }
    if mk_error is None:
        mk = [s["wall_s"] for s in samples["mergekit"]]
        ratios = [o / m for o, m in zip(ours, mk, strict=True)]
        ours_cpu, mk_cpu = (
            per_rep("ours_extract", "ours_merge", metric="cpu_s"),
            per_rep("mergekit", metric="cpu_s"),
        )
        names = ["layers.0.weight", "embed.weight", "layers.1.bias"]
        result["mergekit"].update(
            wall_s={"per_rep": mk, "median": statistics.median(mk), "best": min(mk)},
            peak_rss_mib=best["mergekit"]["peak_rss_mib"],
            ratio={
                "per_rep": ratios,
                "median": statistics.median(ratios),
                "best_to_best": min(ours) / min(mk),
                "cpu_median": statistics.median(o / m for o, m in zip(ours_cpu, mk_cpu, strict=True)),
            },
            agreement=compare_outputs(meta, mk_out, names),
        )
        result["targets"] = {
            "at_most_1x_mergekit": statistics.median(ratios) <= 1.0,
            "rss_below_mergekit": ours_rss < best["mergekit"]["peak_rss_mib"],
        }
        if "before_extract" in samples:
            old = per_rep("before_extract", "before_merge")
            result["before"] = {
                "wall_s": {"per_rep": old, "median": statistics.median(old)},
                "ratio_to_mergekit_median": statistics.median(o / m for o, m in zip(old, mk, strict=True)),
                "peak_rss_mib": max(
                    best["before_extract"]["peak_rss_mib"], best["before_merge"]["peak_rss_mib"]
                ),
            }
    return result


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma-separated, of {', '.join(CASES)}")
    ap.add_argument("--keep", action="store_true", help="keep the synthetic checkpoints")
    ap.add_argument("--work", type=Path, default=WORK, help="scratch directory (checkpoints, mergekit venv)")
    ap.add_argument("--before", help="also time the two commands as of this git revision, in the same run")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    venv = args.work / "mergekit-venv"
    mk_error = ensure_mergekit(venv)
    result = {
        "machine": {
            "python": platform.python_version(),
            "torch": torch.__version__,
            "cpus": os.cpu_count(),
            "load_at_start": os.getloadavg(),
        },
        "cases": {},
    }
    before = checkout(args.before, args.work) if args.before else None
    result["before"] = args.before
    for key in args.cases.split(","):
        result["cases"][key] = run_case(key, args.work, venv, args.reps, mk_error, before)
        if not args.keep:
            shutil.rmtree(args.work / key, ignore_errors=True)
    result["machine"]["load_at_end"] = os.getloadavg()
    write_results(result)


def write_results(r: dict) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "vectors.json").write_text(json.dumps(r, indent=2))
    m = r["machine"]
    lines = [
        "# Vector ops benchmark (bench_vectors.py)",
        "",
        "`capvector vector extract` + `capvector vector merge` as a user runs them (each a fresh process, "
        "a fresh home: inputs imported into the store, outputs registered and placed at `-o`) against "
        "mergekit's `task_arithmetic` (one process, one pass) on the same files, interleaved; each "
        "command's inputs read into page cache (untimed) just before it. Ratios pair the runs of one "
        "repetition; the headline is their median. "
        f"{m['cpus']} cores shared with other jobs: load average {m['load_at_start'][0]:.1f} at the "
        f"start, {m['load_at_end'][0]:.1f} at the end (per case below).",
    ]
    for key, c in r["cases"].items():
        ck, mk, v = c["checkpoint"], c["mergekit"], c["verification"]
        lines += [
            "",
            f"## {c['label']} ({key})",
            "",
            f"{ck['bytes'] / 2**20:.0f} MiB, {ck['tensors']} tensors, {ck['files']} file(s), largest tensor "
            f"{ck['largest_tensor_mib']:.0f} MiB. {c['reps']} repetitions; load average (1 min) "
            f"{c['load_1m']['min']:.1f}–{c['load_1m']['max']:.1f}, median {c['load_1m']['median']:.1f}.",
            "",
            "| command | best wall s | best CPU s | peak RSS MiB |",
            "|---|---|---|---|",
        ]
        for k, b in c["best"].items():
            lines.append(f"| {k} | {b['wall_s']:.2f} | {b['cpu_s']:.2f} | {b['peak_rss_mib']:.0f} |")
        lines.append("")
        if mk["error"]:
            lines.append(f"- mergekit: not measured ({mk['error']}).")
        else:
            t, ratios = c["targets"], ", ".join(f"{x:.2f}" for x in mk["ratio"]["per_rep"])
            met = "met" if t["at_most_1x_mergekit"] else "NOT met"
            lines += [
                f"- **extract + merge: {c['ours_cli_s']['median']:.2f} s vs mergekit "
                f"{mk['wall_s']['median']:.2f} s (medians): ratio {mk['ratio']['median']:.2f}×** (per "
                f"repetition {ratios}; best to best {mk['ratio']['best_to_best']:.2f}×; CPU time "
                f"{mk['ratio']['cpu_median']:.2f}×; target ≤ 1.0×: {met}).",
                f"- peak RSS: ours {c['ours_peak_rss_mib']:.0f} MiB, mergekit {mk['peak_rss_mib']:.0f} MiB "
                f"(below mergekit's: {'yes' if t['rss_below_mergekit'] else 'NO'}).",
                f"- outputs agree to {mk['agreement']['max_rel_diff_sample']:.2g} (normwise relative, "
                "sampled tensors; our two commands round γ to the checkpoint's dtype before merging, "
                "mergekit does not).",
            ]
            if "before" in c:
                b = c["before"]
                lines.append(
                    f"- before (the same commands as of `{r['before']}`, in this run): "
                    f"{b['wall_s']['median']:.2f} s, {b['ratio_to_mergekit_median']:.2f}× mergekit, "
                    f"peak RSS {b['peak_rss_mib']:.0f} MiB."
                )
        runs = zip(v["verified_s"], v["unverified_s"], strict=True)
        pairs = ", ".join(f"{a:.2f}/{b:.2f} s" for a, b in runs)
        lines += [
            f"- verified reads (inputs given as artifact ids, hashed while read and checked against their "
            f"ids) vs the same commands with that check patched out: **{100 * v['cost_median']:+.1f} %** "
            f"of wall time, {100 * v['cpu_cost_median']:+.1f} % of CPU time (medians of {c['reps']} paired "
            f"runs, alternating which goes first; wall {pairs}).",
            f"- library calls alone (no store, no CLI): {statistics.median(c['library']['lib_s']):.2f} s, "
            f"{c['library']['ratio_to_floor_median']:.2f}× their I/O floor (read both inputs, write one "
            "output).",
        ]
    (RESULTS / "vectors.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
