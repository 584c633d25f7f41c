"""What a run's own Prefect API server costs: `capvector run --preset smoke` cold, booting its own server
(no PREFECT_API_URL, as on a user's machine) against the same run told about a server that is already up
(PREFECT_API_URL, as a `prefect server start`, docker-compose's server or the test suite's one per worker).

Run: .venv/bin/python benchmarks/bench_run_server.py [--rounds 2]
Writes benchmarks/results/run_server.{md,json}. Scratch homes go to benchmarks/_work (git-ignored) and
are deleted afterwards.

Each run gets a fresh home and cache folder, so both compute every step. Both use one Prefect home,
migrated before the first round, so neither pays for a first start. CPU is user + system time of the
CLI and everything it waited for (its step workers, its own server), from getrusage of the children;
for the shared server, the CPU it spent during the run (from /proc) is added. The two alternate round
by round, so a busy machine slows both alike.
"""

import argparse
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
WORK = HERE / "_work" / "run_server"
RESULTS = HERE / "results"
sys.path.insert(0, str(REPO))

from capvector.flows.runtime.prefect_server import RunServer  # noqa: E402


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _process_cpu(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _smoke_run(name: str, env: dict[str, str], server: RunServer | None) -> tuple[float, float]:
    """(wall s, CPU s) of one cold smoke run in a home of its own."""
    home = WORK / name
    shutil.rmtree(home, ignore_errors=True)
    env = {**env, "CAPVECTOR_HOME": str(home / "home"), "CAPVECTOR_CACHE": str(home / "cache")}
    served_before = _process_cpu(server.process.pid) if server else 0.0
    cpu_before, started = _children_cpu(), time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "capvector", "run", "--preset", "smoke", "--json"],
        cwd=REPO, env=env, capture_output=True, text=True,
    )  # fmt: skip
    wall = time.perf_counter() - started
    served = _process_cpu(server.process.pid) - served_before if server else 0.0
    cpu = _children_cpu() - cpu_before + served
    if proc.returncode != 0:
        raise RuntimeError(f"{name} failed: {proc.stderr[-3000:]}")
    shutil.rmtree(home, ignore_errors=True)
    return wall, cpu


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()

    WORK.mkdir(parents=True, exist_ok=True)
    prefect_home = WORK / "prefect"
    shutil.rmtree(prefect_home, ignore_errors=True)
    os.environ["PREFECT_HOME"] = str(prefect_home)
    os.environ.pop("PREFECT_API_URL", None)
    base = {**os.environ, "CAPVECTOR_QUIET": "1", "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}

    server = RunServer()
    boot_started = time.perf_counter()
    server.wait_ready()  # also migrates the Prefect home both variants use
    boot = {"wall_s": time.perf_counter() - boot_started, "cpu_s": _process_cpu(server.process.pid)}
    shared = {**base, "PREFECT_API_URL": server.url}
    variants = {"own server": (base, None), "shared server": (shared, server)}
    runs: dict[str, list[tuple[float, float]]] = {name: [] for name in variants}
    try:
        for r in range(args.rounds):
            for name in variants if r % 2 == 0 else reversed(variants):
                env, srv = variants[name]
                runs[name].append(_smoke_run(f"{name.replace(' ', '-')}-{r}", env, srv))
                print(f"round {r + 1}/{args.rounds} {name}: {runs[name][-1][0]:.1f} s wall, "
                      f"{runs[name][-1][1]:.1f} s CPU", flush=True)  # fmt: skip
    finally:
        server.stop()

    med = {
        name: {"wall_s": statistics.median(w for w, _ in rs), "cpu_s": statistics.median(c for _, c in rs)}
        for name, rs in runs.items()
    }
    own, shared_med = med["own server"], med["shared server"]
    result = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
        "date": time.strftime("%Y-%m-%d"),
        "rounds": args.rounds,
        "server_boot": boot,
        "median": med,
        "all": {name: [{"wall_s": w, "cpu_s": c} for w, c in rs] for name, rs in runs.items()},
        "cpu_ratio_own_over_shared": own["cpu_s"] / shared_med["cpu_s"],
        "wall_ratio_own_over_shared": own["wall_s"] / shared_med["wall_s"],
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "run_server.json").write_text(json.dumps(result, indent=1) + "\n")
    lines = [
        "# A run's own Prefect server against one already up",
        "",
        f"`benchmarks/bench_run_server.py`, {result['date']}, {result['machine']}; `capvector run --preset "
        f"smoke` cold in a fresh home, {args.rounds} rounds alternating the order, medians (the machine was "
        "shared with a study).",
        "",
        "| the run | wall | CPU (CLI, workers, server) |",
        "|---|---|---|",
        *(f"| {name} | {m['wall_s']:.1f} s | {m['cpu_s']:.1f} s |" for name, m in med.items()),
        "",
        f"Booting a server alone: {boot['wall_s']:.1f} s wall, {boot['cpu_s']:.1f} s CPU. A run with its own "
        f"server costs **{result['cpu_ratio_own_over_shared']:.2f}×** the CPU and "
        f"{result['wall_ratio_own_over_shared']:.2f}× the wall time of one told about a running server "
        "(`PREFECT_API_URL`). The test suite gives each pytest-xdist worker one server for this reason.",
        "",
    ]
    (RESULTS / "run_server.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
