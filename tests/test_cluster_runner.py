"""`--runner dask --address`: the steps of a run go to an existing Dask scheduler's workers, on
loopback here (`dask scheduler` and two `dask worker` processes, one offering GPU=1), and give the
same artifact ids as the default process pool. A step whose config asks for cuda runs only on the
worker that offers a GPU (scheduling only: nothing here touches a GPU). The cluster: conftest's `cluster`."""

import json
import os
import re
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest
from conftest import REPO, run_cli

from capvector.flows.runtime.task_runners import RunnerConfig, runner_config
from capvector.flows.study.plan import study_plan
from capvector.flows.study.recipe import recipe_study

TESTS = REPO / "tests"


def _executed(address: str) -> dict[str, int]:
    """Tasks each worker has executed since it started."""
    from distributed import Client

    with Client(address, timeout=30) as client:
        return client.run(lambda dask_worker: dask_worker.state.executed_count)


def test_cuda_steps_run_only_on_the_gpu_worker(cluster):
    """Two runs, each with its own Prefect server (as two CLI runs have), on the same long-lived
    workers: the second one once failed every step, its workers still asking the first run's server
    for the tags' concurrency slots."""
    address, _, gpu = cluster
    for attempt in ("first run", "second run"):
        proc = subprocess.run(
            [sys.executable, str(TESTS / "gpu_placement_probe.py"), address, "4"],
            cwd=REPO,
            env={**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{TESTS}", "CAPVECTOR_QUIET": "1"},
            capture_output=True,
            text=True,
            timeout=300,
            start_new_session=True,
        )
        assert proc.returncode == 0, f"{attempt}: {proc.stderr[-3000:]}"
        ran_on = json.loads(proc.stdout.strip().splitlines()[-1])
        assert len(ran_on) == 8
        cuda = {step: worker for step, worker in ran_on.items() if step.startswith("cuda")}
        cpu = {step: worker for step, worker in ran_on.items() if step.startswith("cpu")}
        assert set(cuda.values()) == {gpu}, ran_on
        assert set(cpu.values()) - {gpu}, ran_on  # the other worker took cpu steps: the GPU one was asked for


def _lineage(home: str | Path, artifact_id: str, cache: Path | None = None) -> set[tuple[str, str]]:
    env = {"CAPVECTOR_CACHE": str(cache)} if cache else None
    rows = json.loads(run_cli("lineage", artifact_id, "--format", "json", home=home, env=env).stdout)
    return {(row["id"], row["kind"]) for row in rows}


def test_smoke_run_with_an_s3_home_on_the_cluster(cluster, smoke_home, tmp_path):
    """The home on S3, the steps on the cluster's workers (each with its own local cache, as other
    machines): the process pool's ids, lineage complete the moment the run returns, and a rerun, also
    from a fresh driver that never saw the home, dispatches nothing."""
    import boto3

    address, logs, _ = cluster
    bucket = f"capvector-{uuid.uuid4().hex[:12]}"
    boto3.client("s3").create_bucket(Bucket=bucket)
    home = f"s3://{bucket}/home"
    driver = {"CAPVECTOR_QUIET": "0", "CAPVECTOR_CACHE": str(tmp_path / "driver-cache")}
    runner = ["--runner", "dask", "--address", address, "--json"]

    before = _executed(address)
    started = time.monotonic()
    proc = run_cli("run", "--preset", "smoke", *runner, home=home, env=driver, timeout=600)
    elapsed = time.monotonic() - started
    ids = json.loads(proc.stdout)
    local = smoke_home[1]
    assert {k: v for k, v in ids.items() if k != "report_file"} == {
        k: v for k, v in local.items() if k != "report_file"
    }
    # the Markdown report: in the driver's cache of the home, not in a local folder `s3:` of the cwd
    assert Path(ids["report_file"]).is_relative_to(tmp_path / "driver-cache"), ids["report_file"]

    from capvector.flows.recipe.config import load_config

    after = _executed(address)
    ran = {worker: after[worker] - before.get(worker, 0) for worker in after}
    steps = len(study_plan(recipe_study(load_config("smoke", None))))
    assert sum(ran.values()) == steps, ran  # every step, on a worker
    worker_logs = "\n".join(log.read_text() for log in logs.values())
    assert "[pretrain θ_pt] 30/30 steps" in worker_logs  # a step's progress, printed where it ran

    # the terminal: progress lines, no Dask or Prefect INFO records, no teardown noise
    assert f"[study smoke {steps}/{steps}]" in proc.stderr
    assert not re.search(r" - INFO - |\| INFO +\|", proc.stderr), proc.stderr[-3000:]
    assert "killed by signal" not in proc.stderr and "Traceback" not in proc.stderr, proc.stderr[-3000:]

    # what the workers registered is in the driver's catalogue at once: the local run's lineage
    assert _lineage(home, ids["report"], tmp_path / "driver-cache") == _lineage(smoke_home[0], ids["report"])

    for name, cache in (("rerun", "driver-cache"), ("fresh driver", "fresh-driver-cache")):
        before = _executed(address)
        env = {"CAPVECTOR_CACHE": str(tmp_path / cache)}
        proc = run_cli("run", "--preset", "smoke", *runner, home=home, env=env, timeout=600)
        again = json.loads(proc.stdout)
        assert Path(again.pop("report_file")).is_relative_to(tmp_path / cache), name  # each driver's own
        assert again == {k: v for k, v in ids.items() if k != "report_file"}, name
        assert _executed(address) == before, f"{name}: steps were sent to the workers again"
    print(f"smoke run on the dask cluster with an S3 home: {elapsed:.0f} s, steps per worker {ran}")


def test_runner_options_are_checked():
    assert RunnerConfig().kind == "process" and RunnerConfig().workers == 2
    config = runner_config("dask", None, 3, "distributed.LocalCluster", '{"n_workers": 1}')
    assert config.cluster_kwargs == {"n_workers": 1}
    bad = {
        ("dask", "127.0.0.1:8786", None, None): "starts with tcp://",
        ("dask", None, "nowhere.Cluster", None): "--cluster-class: cannot import 'nowhere.Cluster'",
        ("dask", None, None, "[1]"): "must be a JSON object",
        ("dask", "tcp://h:1", None, '{"n_workers": 2}'): "no --cluster-class/--cluster-kwargs",
        ("process", "tcp://h:1", None, None): "--address is for --runner dask or ray",
        ("gpu", None, None, None): "--runner: Input should be",
    }
    for (kind, address, cluster_class, kwargs), message in bad.items():
        with pytest.raises(ValueError, match=re.escape(message)):
            runner_config(kind, address, 2, cluster_class, kwargs)
    try:
        import prefect_ray  # noqa: F401
    except ImportError:
        with pytest.raises(ValueError, match="pip install prefect-ray"):
            runner_config("ray", None, 2, None, None)
