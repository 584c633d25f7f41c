"""Cold and warm `capvector run` wall times, Prefect API servers per run, Prefect's fixed overhead.

    python benchmarks/bench_pipeline.py [--presets smoke] [--warm-reps 3] [--work-dir DIR] [--before REV]

With `--before REV` the same cold and warm runs are made, in the same session, with the code of REV (a
temporary git worktree; the warm runs of both alternate), so the warm run's speed-up is measured
against an earlier revision on the same machine at the same time.

Cold: a fresh home and a fresh Prefect home. Warm: the same command again, every step a cache hit
(median of --warm-reps). While each run goes, its process tree is sampled every 0.1 s: the Prefect
API servers (uvicorn serving prefect.server) and the step workers it ever had are counted, and the CPU
time of every process in it is summed (wall time depends on what else the machine runs; CPU much less).
Prefect's fixed overhead: a plain process that imports our flows and runs one empty flow on Prefect's
own embedded server, against one that only imports them.
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
from datetime import UTC, datetime
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
RESULTS = REPO / "benchmarks" / "results"

EMPTY_FLOW = """
import capvector.flows.study.flow
from prefect import flow
@flow
def empty():
    return 1
empty()
"""
IMPORT_ONLY = "import capvector.flows.study.flow"


def _stat(pid: int) -> list[str] | None:
    """The fields of /proc/<pid>/stat after the command name (state, ppid, …, utime at 11, stime at 12)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def _children() -> dict[int, list[int]]:
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        fields = _stat(int(stat.parent.name))
        if fields:
            children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    return children


def _descendants(root: int) -> dict[int, tuple[int, str]]:
    """{pid: (parent pid, command line)} of every live process below `root`."""
    children, found, frontier = _children(), {}, [root]
    while frontier:
        parent = frontier.pop()
        for pid in children.get(parent, []):
            try:
                found[pid] = (parent, Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode())
            except OSError:
                continue
            frontier.append(pid)
    return found


def _is_pool_worker(parent: int, cmdline: str, tree: dict[int, tuple[int, str]]) -> bool:
    """A spawned worker runs spawn_main (the resource tracker does not); a forked one is a child of the
    fork server and shows the server's command line."""
    if "spawn_main" in cmdline:
        return True
    server = "multiprocessing.forkserver"
    return server in cmdline and server in tree.get(parent, (0, ""))[1]


def timed(cmd: list[str], env: dict[str, str], cwd: Path = REPO) -> dict[str, float]:
    """Wall time of one command, the CPU time of its whole process tree (user + system, each process's
    last reading, sampled every 0.1 s), and the servers and workers seen in that tree."""
    servers: set[int] = set()
    workers: set[int] = set()
    cpu: dict[int, float] = {}
    tick = os.sysconf("SC_CLK_TCK")
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    while proc.poll() is None:
        tree = _descendants(proc.pid)
        for pid in [proc.pid, *tree]:
            fields = _stat(pid)
            if fields:
                cpu[pid] = max(cpu.get(pid, 0.0), (int(fields[11]) + int(fields[12])) / tick)
        for pid, (parent, cmdline) in tree.items():
            if "uvicorn" in cmdline and "prefect.server" in cmdline:
                servers.add(pid)
            elif _is_pool_worker(parent, cmdline, tree):
                workers.add(pid)
        time.sleep(0.1)
    wall = time.perf_counter() - start
    if proc.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed with code {proc.returncode}")
    return {"wall_s": wall, "cpu_s": sum(cpu.values()), "servers": len(servers), "workers": len(workers)}


def verification_bound_s(home: Path) -> tuple[float, int]:
    """Seconds to hash every stored file once, and their total bytes. A run verifies an artifact at
    most once per process that reads it (the CLI and two workers), so 3x this bounds its cost."""
    from capvector.artifacts.hashing import hash_file

    files = [p for p in (home / "store").rglob("*") if p.is_file() and not p.name.endswith(".json")]
    start = time.perf_counter()
    for path in files:
        hash_file(str(path))
    return time.perf_counter() - start, sum(p.stat().st_size for p in files)


def environment(work: Path, name: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    return {
        **env,
        "CAPVECTOR_HOME": str(work / f"{name}-home"),
        "PREFECT_HOME": str(work / f"{name}-prefect"),
        "CAPVECTOR_QUIET": "1",
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
        "DO_NOT_TRACK": "1",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--presets", nargs="+", default=["smoke"])
    parser.add_argument("--warm-reps", type=int, default=3)
    parser.add_argument("--work-dir", type=Path, default=None)
    parser.add_argument("--before", default=None, help="also time the code of this revision (a worktree)")
    args = parser.parse_args()
    work = args.work_dir or Path(tempfile.mkdtemp(prefix="capvector-bench-pipeline-"))
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    load_start = os.getloadavg()[0]

    overhead_env = environment(work, "overhead")
    import_only = timed([sys.executable, "-c", IMPORT_ONLY], overhead_env)["wall_s"]
    first_flow = timed([sys.executable, "-c", EMPTY_FLOW], overhead_env)["wall_s"]  # new Prefect DB
    later_flow = timed([sys.executable, "-c", EMPTY_FLOW], overhead_env)["wall_s"]
    rows = []
    for preset in args.presets:
        env = environment(work, preset)
        cmd = [sys.executable, "-m", "capvector", "run", "--preset", preset, "--json"]
        if args.before:
            cold, warms, before = _with_before(args.before, work, preset, cmd, env, args.warm_reps)
        else:
            cold = timed(cmd, env)
            warms, before = [timed(cmd, env) for _ in range(args.warm_reps)], None
        warm = statistics.median(w["wall_s"] for w in warms)
        hash_s, stored = verification_bound_s(Path(env["CAPVECTOR_HOME"]))
        rows.append(
            {
                "preset": preset,
                "cold_s": cold["wall_s"],
                "cold_cpu_s": cold["cpu_s"],
                "warm_s": warm,
                "warm_runs_s": [w["wall_s"] for w in warms],
                "warm_over_cold": warm / cold["wall_s"],
                "servers_cold": cold["servers"],
                "servers_warm": max(w["servers"] for w in warms),
                "workers_cold": cold["workers"],
                "workers_warm": max(w["workers"] for w in warms),
                "stored_bytes": stored,
                "hash_all_once_s": hash_s,
                "verification_bound_over_cold": 3 * hash_s / cold["wall_s"],
                **({"before": before, "warm_speedup": before["warm_s"] / warm} if before else {}),
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    overhead = {
        "import_only_s": import_only,
        "empty_flow_new_prefect_db_s": first_flow,
        "empty_flow_s": later_flow,
        "prefect_fixed_overhead_s": later_flow - import_only,
    }
    print(json.dumps(overhead, indent=1))
    result = {
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, "
        f"load average {load_start:.1f} at the start, {os.getloadavg()[0]:.1f} at the end",
        "runs": rows,
        "prefect": overhead,
    }
    (RESULTS / "pipeline.json").write_text(json.dumps(result, indent=1) + "\n")
    lines = [
        "# Pipeline wall time (bench_pipeline.py)",
        "",
        f"{result['date']}; {result['machine']}. Each run is a fresh `python -m capvector run` process;",
        f"warm is the median of {args.warm_reps} runs. Servers and workers: distinct Prefect API server",
        "and pool-worker processes seen in the run's process tree.",
        "",
        "| preset | cold s | cold CPU s | warm s (all cache hits) | warm / cold | servers cold / warm "
        "| workers cold / warm |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['preset']} | {r['cold_s']:.1f} | {r['cold_cpu_s']:.1f} | {r['warm_s']:.1f} | "
            f"**{r['warm_over_cold']:.2f}** | "
            f"{r['servers_cold']} / {r['servers_warm']} | {r['workers_cold']} / {r['workers_warm']} |"
        )
    for r in rows:
        if "before" in r:
            b = r["before"]
            lines.append(
                f"\nThe same runs with the code of `{b['rev']}`, in this session: cold {b['cold_s']:.1f} s "
                f"and {b['cold_cpu_s']:.1f} s of CPU ({b['workers_cold']} workers), warm {b['warm_s']:.1f} s "
                f"(warm / cold {b['warm_s'] / b['cold_s']:.2f}), servers cold / warm {b['servers_cold']} / "
                f"{b['servers_warm']}. Now the cold run takes **{r['cold_cpu_s'] / b['cold_cpu_s']:.2f}×** "
                f"the CPU and the warm run is **{r['warm_speedup']:.2f}×** as fast."
            )
    for r in rows:
        lines.append(
            f"\nVerified reads, {r['preset']}: hashing every stored file once "
            f"({r['stored_bytes'] / 2**20:.1f} MiB) "
            f"takes {r['hash_all_once_s']:.3f} s; a run re-hashes an artifact at most once per process that "
            f"reads it (CLI + 2 workers), so verification costs at most "
            f"**{100 * r['verification_bound_over_cold']:.2f} %** of the cold run (target < 5 %)."
        )
    lines += [
        "",
        "Prefect's fixed overhead, same run: importing our flows takes "
        f"{import_only:.1f} s; a plain process that also runs one empty flow on Prefect's own embedded "
        f"server takes {later_flow:.1f} s ({first_flow:.1f} s with a brand-new Prefect database): a "
        f"server start costs about **{overhead['prefect_fixed_overhead_s']:.1f} s**. A run that has a "
        "step to do starts one (on a new home at once, booting while the CLI imports; else once the "
        "cache probe found a step to run). A warm run is answered from the cache before any flow "
        "starts and starts no server (its address is reserved before Prefect is imported, the process "
        "is not spawned): the imports, not the steps, are what a warm run costs.",
        "",
    ]
    (RESULTS / "pipeline.md").write_text("\n".join(lines))
    shutil.rmtree(work, ignore_errors=True)


def _with_before(
    rev: str, work: Path, preset: str, cmd: list[str], env: dict[str, str], reps: int
) -> tuple[dict, list[dict], dict]:
    """Cold and warm runs of this code and of `rev` (a temporary worktree, its own homes), the warm
    runs alternating between the two so that a machine that gets busier slows both alike."""
    tree = work / "before-tree"
    subprocess.run(["git", "worktree", "add", "--detach", "-f", str(tree), rev], cwd=REPO, check=True)
    try:
        env_before = {**environment(work, f"before-{preset}"), "PYTHONPATH": str(tree)}
        cold, cold_before = timed(cmd, env), timed(cmd, env_before, cwd=tree)
        warms, warms_before = [], []
        for _ in range(reps):
            warms.append(timed(cmd, env))
            warms_before.append(timed(cmd, env_before, cwd=tree))
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=REPO, check=False)
    before = {
        "rev": rev,
        "cold_s": cold_before["wall_s"],
        "cold_cpu_s": cold_before["cpu_s"],
        "workers_cold": cold_before["workers"],
        "warm_s": statistics.median(w["wall_s"] for w in warms_before),
        "warm_runs_s": [w["wall_s"] for w in warms_before],
        "servers_cold": cold_before["servers"],
        "servers_warm": max(w["servers"] for w in warms_before),
    }
    return cold, warms, before


if __name__ == "__main__":
    main()
