"""Test helper: a cluster on this machine (Dask's scheduler and workers, or Ray's head and worker
nodes), and the checks the Dask and Ray tests share: a smoke run on the cluster gives the process
pool's artifact ids with every step run on a worker, and steps asking for cuda run only on the worker
that offers a GPU (scheduling only: nothing touches a GPU).

Each cluster process runs in a session and HOME of its own, imports this repository (and tests/,
for gpu_placement_probe) and is ended by its process group, never by name (`ray stop` would end
every Ray process of the user on the machine)."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from conftest import REPO, own_server_env, run_cli

TESTS = REPO / "tests"


@dataclass
class LoopbackCluster:
    """A running cluster, as the tests see it."""

    engine: str  # "dask" | "ray": the CLI's --runner
    address: str  # the CLI's --address
    gpu: str  # the worker offering a GPU: a Dask worker's address, a Ray node's id
    executed: Callable[[], dict[str, int]]  # steps each worker has run since it started
    worker_output: Callable[[], str]  # what the workers printed so far

    @property
    def runner(self) -> list[str]:
        return ["--runner", self.engine, "--address", self.address]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(
    argv: list[str], root: Path, name: str, env: dict[str, str] | None = None
) -> tuple[subprocess.Popen, Path]:
    """`argv[0]` (a console script of this environment: dask, ray) in its own session and HOME, with
    this repository and tests/ on its path, and `env`; output to `root/name.log`."""
    extra = env or {}
    home = root / name
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    env.update(HOME=str(home), PREFECT_HOME=str(home / "prefect"), PYTHONPATH=f"{REPO}{os.pathsep}{TESTS}")
    env.update(RAY_USAGE_STATS_ENABLED="0", **extra)  # a Ray node reports nothing home
    log = root / f"{name}.log"
    proc = subprocess.Popen(
        [str(Path(sys.executable).with_name(argv[0])), *argv[1:]],
        cwd=REPO,
        env=env,
        stdout=log.open("wb"),
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    return proc, log


def stop(proc: subprocess.Popen, grace_s: float = 30) -> None:
    """End `proc`'s process group: SIGTERM, then SIGKILL for what is left (a nanny's worker, a
    raylet's workers)."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            pass
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait(timeout=30)


def lineage(home: str | Path, artifact_id: str, cache: Path | None = None) -> set[tuple[str, str]]:
    env = {"CAPVECTOR_CACHE": str(cache)} if cache else None
    rows = json.loads(run_cli("lineage", artifact_id, "--format", "json", home=home, env=env).stdout)
    return {(row["id"], row["kind"]) for row in rows}


def smoke_steps() -> int:
    """How many steps `capvector run --preset smoke` plans (the recipe as the smallest study)."""
    from capvector.flows.recipe.config import load_config
    from capvector.flows.study.plan import study_plan
    from capvector.flows.study.recipe import recipe_study

    return len(study_plan(recipe_study(load_config("smoke", None))))


def without_report_file(ids: dict[str, str]) -> dict[str, str]:
    """A run's `--json` less `report_file`: the Markdown report's path, in the cache of the run's home."""
    return {k: v for k, v in ids.items() if k != "report_file"}


def wait_for_executed(cluster: LoopbackCluster, before: dict[str, int], steps: int) -> dict[str, int]:
    """Steps each worker ran since `before`, once they add up to `steps` (Ray records a finished task
    a moment after its result is back) or after 30 s."""
    deadline = time.monotonic() + 30
    while True:
        after = cluster.executed()
        ran = {worker: after[worker] - before.get(worker, 0) for worker in after}
        if sum(ran.values()) >= steps or time.monotonic() > deadline:
            return ran
        time.sleep(0.5)


def check_smoke_run_with_an_s3_home(
    cluster: LoopbackCluster,
    smoke_home,
    tmp_path: Path,
    while_running=None,
    retries: int = 0,
    reruns: bool = True,
) -> subprocess.CompletedProcess:
    """The home on S3, the steps on the cluster's workers (each with its own local cache, as other
    machines): the process pool's ids, lineage complete the moment the run returns, and (`reruns`) a
    rerun, also from a fresh driver that never saw the home, dispatches nothing. `while_running(proc)`
    interferes with the first run (kills a worker), which then executes `retries` steps a second time;
    that run's output is returned."""
    import boto3

    bucket = f"capvector-{uuid.uuid4().hex[:12]}"
    boto3.client("s3").create_bucket(Bucket=bucket)
    home = f"s3://{bucket}/home"
    driver = {"CAPVECTOR_QUIET": "0", "CAPVECTOR_CACHE": str(tmp_path / "driver-cache")}
    runner = [*cluster.runner, "--json"]

    before = cluster.executed()
    started = time.monotonic()
    proc = run_cli(
        "run", "--preset", "smoke", *runner, home=home, env=driver, timeout=600, while_running=while_running
    )
    first = proc
    elapsed = time.monotonic() - started
    ids = json.loads(proc.stdout)
    assert without_report_file(ids) == without_report_file(smoke_home[1])
    # the Markdown report: in the driver's cache of the home, not in a local folder `s3:` of the cwd
    assert Path(ids["report_file"]).is_relative_to(tmp_path / "driver-cache"), ids["report_file"]

    steps = smoke_steps()
    ran = wait_for_executed(cluster, before, steps + retries)
    assert sum(ran.values()) == steps + retries, ran  # every step, on a worker (and each retry)
    assert "[pretrain θ_pt] 30/30 steps" in cluster.worker_output()  # a step's progress, printed where it ran

    # the terminal: progress lines, no engine or Prefect INFO records, no teardown noise
    assert f"[study smoke {steps}/{steps}]" in proc.stderr
    assert not re.search(r" - INFO - |\| INFO +\||\tINFO ", proc.stderr), proc.stderr[-3000:]
    assert "killed by signal" not in proc.stderr and "Traceback" not in proc.stderr, proc.stderr[-3000:]

    # what the workers registered is in the driver's catalogue at once: the local run's lineage
    assert lineage(home, ids["report"], tmp_path / "driver-cache") == lineage(smoke_home[0], ids["report"])

    for name, cache in (("rerun", "driver-cache"), ("fresh driver", "fresh-driver-cache")) if reruns else ():
        before = cluster.executed()
        env = {"CAPVECTOR_CACHE": str(tmp_path / cache)}
        proc = run_cli("run", "--preset", "smoke", *runner, home=home, env=env, timeout=600)
        again = json.loads(proc.stdout)
        assert Path(again.pop("report_file")).is_relative_to(tmp_path / cache), name  # each driver's own
        assert again == without_report_file(ids), name
        assert cluster.executed() == before, f"{name}: steps were sent to the workers again"
    print(f"smoke run on the {cluster.engine} cluster, S3 home: {elapsed:.0f} s, steps per worker {ran}")
    return first


def check_cuda_steps_run_only_on_the_gpu_worker(
    cluster: LoopbackCluster, addresses: list[str], n: int
) -> None:
    """One probe run per address, each with its own Prefect server (as two CLI runs have), on the same
    long-lived workers: on Dask the second one once failed every step, its workers still asking the
    first run's server for the tags' concurrency slots."""
    # the probe boots its own Prefect server (not the test session's), as each CLI run on its own does
    probe_env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{TESTS}", "CAPVECTOR_QUIET": "1"}
    probe_env = own_server_env(probe_env)
    for attempt, address in enumerate(addresses, 1):
        proc = subprocess.run(
            [sys.executable, str(TESTS / "gpu_placement_probe.py"), cluster.engine, address, str(n)],
            cwd=REPO,
            env=probe_env,
            capture_output=True,
            text=True,
            timeout=300,
            start_new_session=True,
        )
        assert proc.returncode == 0, f"run {attempt} ({address}): {proc.stderr[-3000:]}"
        ran_on = json.loads(proc.stdout.strip().splitlines()[-1])
        assert len(ran_on) == 2 * n
        cuda = {step: worker for step, worker in ran_on.items() if step.startswith("cuda")}
        cpu = {step: worker for step, worker in ran_on.items() if step.startswith("cpu")}
        assert set(cuda.values()) == {cluster.gpu}, ran_on
        # the other worker took cpu steps: the GPU one was asked for, not the only one there
        assert set(cpu.values()) - {cluster.gpu}, ran_on
