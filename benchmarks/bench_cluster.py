"""A study on a Dask cluster against the default process pool: wall time and overhead per step.

    python benchmarks/bench_cluster.py [--preset study-smoke] [--rounds 2] [--work-dir DIR]

On loopback: a `dask scheduler` and two `dask worker` processes (one thread each, their own HOME), as a
user's cluster would be, against `capvector study`'s default pool of 2 step processes on the same
2 cores. Each round runs the preset cold on a fresh home once per runner (the order alternates between
rounds), then once more warm (every step cached: nothing is dispatched). Overhead per step = (cluster
wall − pool wall) / steps the cold study ran on the workers. The cluster's start-up (scheduler and
workers) is timed apart: a cluster is started once and serves many studies.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "benchmarks" / "results"
DASK = str(Path(sys.executable).with_name("dask"))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def base_env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    return {**env, "CAPVECTOR_QUIET": "1", "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DO_NOT_TRACK": "1"}


class Cluster:
    """A scheduler and two single-threaded workers, each in its own session, HOME and folder."""

    def __init__(self, root: Path):
        self.address = f"tcp://127.0.0.1:{free_port()}"
        self.root, self.procs = root, []

    def __enter__(self) -> Cluster:
        from distributed import Client

        start = time.perf_counter()
        port = self.address.rsplit(":", 1)[1]
        self._spawn("scheduler", ["scheduler", "--host", "127.0.0.1", "--port", port, "--no-dashboard"])
        for name in ("worker-a", "worker-b"):
            folder = self.root / name
            args = ["worker", self.address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard"]
            self._spawn(name, [*args, "--local-directory", str(folder)])
        with Client(self.address, timeout=120) as client:
            client.wait_for_workers(2, timeout=120)
        self.start_s = time.perf_counter() - start
        return self

    def _spawn(self, name: str, args: list[str]) -> None:
        home = self.root / name
        home.mkdir(parents=True, exist_ok=True)
        env = {
            **base_env(),
            "HOME": str(home),
            "PREFECT_HOME": str(home / "prefect"),
            "PYTHONPATH": str(REPO),
        }
        log = (self.root / f"{name}.log").open("wb")
        self.procs.append(
            subprocess.Popen(
                [DASK, *args], cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
            )  # fmt: skip
        )

    def executed(self) -> int:
        from distributed import Client

        with Client(self.address, timeout=30) as client:
            return sum(client.run(lambda dask_worker: dask_worker.state.executed_count).values())

    def __exit__(self, *exc) -> None:
        for proc in reversed(self.procs):
            try:
                os.killpg(proc.pid, 15)
                proc.wait(timeout=30)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                pass


def study(preset: str, home: Path, runner: list[str]) -> tuple[float, dict]:
    """Wall seconds of one `capvector study` and its JSON answer."""
    env = {**base_env(), "PREFECT_HOME": str(home.with_name(home.name + "-prefect"))}
    cmd = [sys.executable, "-m", "capvector", "study", "--preset", preset, "--home", str(home), "--json"]
    start = time.perf_counter()
    proc = subprocess.run([*cmd, *runner], cwd=REPO, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if proc.returncode:
        raise SystemExit(f"{' '.join(cmd + runner)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return wall, json.loads(proc.stdout)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="study-smoke")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--work-dir", type=Path)
    ap.add_argument("--from-json", action="store_true", help="re-render results/cluster.md from its JSON")
    args = ap.parse_args()
    if args.from_json:
        write_markdown(json.loads((RESULTS / "cluster.json").read_text()))
        return
    sys.path.insert(0, str(REPO))
    from capvector.flows.study.config import load_study
    from capvector.flows.study.plan import study_steps

    steps = sum(study_steps(load_study(args.preset)))  # before the gate + after it (if it passes)
    work = args.work_dir or Path(tempfile.mkdtemp(prefix="bench-cluster-"))
    load_before = os.getloadavg()[0]
    rows: dict[str, dict[str, list[float]]] = {
        "pool": {"cold": [], "warm": []},
        "cluster": {"cold": [], "warm": []},
    }
    answers, dispatched = {}, {}
    with Cluster(work / "cluster") as cluster:
        for r in range(args.rounds):
            order = ["pool", "cluster"] if r % 2 == 0 else ["cluster", "pool"]
            for name in order:
                runner = ["--runner", "dask", "--address", cluster.address] if name == "cluster" else []
                home = work / f"{name}-{r}"
                before = cluster.executed()
                for phase in ("cold", "warm"):
                    wall, answers[name] = study(args.preset, home, runner)
                    rows[name][phase].append(wall)
                    print(f"round {r} {name} {phase}: {wall:.1f} s", flush=True)
                dispatched[name] = cluster.executed() - before
        start_s = cluster.start_s
    same = answers["pool"]["report"] == answers["cluster"]["report"]
    med = {n: {p: statistics.median(v) for p, v in ph.items()} for n, ph in rows.items()}
    ran = dispatched["cluster"]  # the steps a cold study ran (a gate may stop it before the plan's total)
    overhead = (med["cluster"]["cold"] - med["pool"]["cold"]) / ran
    result = {
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}",
        "preset": args.preset, "steps": steps, "rounds": args.rounds, "walls": rows, "medians": med,
        "cluster_start_s": start_s, "overhead_per_step_s": overhead, "same_answer": same,
        "steps_on_cluster_workers_last_round": dispatched,
        "load_average": [load_before, os.getloadavg()[0]],
    }  # fmt: skip
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "cluster.json").write_text(json.dumps(result, indent=1) + "\n")
    write_markdown(result)


def write_markdown(result: dict) -> None:
    """results/cluster.md from a result (`--from-json` re-renders the committed one)."""
    walls, med, dispatched = result["walls"], result["medians"], result["steps_on_cluster_workers_last_round"]
    ran = dispatched["cluster"]
    diff = med["cluster"]["cold"] - med["pool"]["cold"]
    spread = max(max(w["cold"]) - min(w["cold"]) for w in walls.values())
    verdict = (
        "no measurable difference (the medians differ by less than one runner's spread between rounds)"
        if abs(diff) < spread
        else f"{diff / ran * 1000:+.0f} ms per step"
    )
    cells = {n: ", ".join(f"{w:.1f}" for w in walls[n]["cold"]) for n in walls}
    load = result["load_average"]
    lines = [
        "# A study on a Dask cluster against the process pool",
        "",
        f"`benchmarks/bench_cluster.py --preset {result['preset']} --rounds {result['rounds']}`, "
        f"{result['date'][:10]}, {result['machine']}; load average {load[0]:.1f} at the start, "
        f"{load[1]:.1f} at the end.",
        f"Loopback cluster: `dask scheduler` + 2 `dask worker` (1 thread each, own HOME), started once in "
        f"{result['cluster_start_s']:.1f} s; the pool: `capvector study`'s default 2 step processes. "
        f"{result['steps']} planned steps, {ran} run; each round runs both cold on fresh homes (order "
        "alternating), then warm. Medians over rounds; the cold runs of each round listed.",
        "",
        "| runner | cold s (median) | cold s (rounds) | warm s | steps run on cluster workers (last round) |",
        "|---|---|---|---|---|",
        f"| process pool (default) | {med['pool']['cold']:.1f} | {cells['pool']} | "
        f"{med['pool']['warm']:.1f} | {dispatched['pool']} |",
        f"| `--runner dask --address` | {med['cluster']['cold']:.1f} | {cells['cluster']} | "
        f"{med['cluster']['warm']:.1f} | {dispatched['cluster']} |",
        "",
        f"**Cluster / pool, cold: {med['cluster']['cold'] / med['pool']['cold']:.2f}×: {verdict}.** "
        f"Same report id from both: {result['same_answer']}. A warm rerun on the cluster dispatches "
        "nothing (its steps are answered from the cache before any flow starts). Both runners do the "
        "same work on the same cores, so this measures orchestration, not parallelism.",
    ]  # fmt: skip
    (RESULTS / "cluster.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
