"""`--runner dask --address`: the steps of a run go to an existing Dask scheduler's workers, on
loopback here (`dask scheduler` and two `dask worker` processes, one offering GPU=1), and give the
same artifact ids as the default process pool. A step whose config asks for cuda runs only on the
worker that offers a GPU (scheduling only: nothing here touches a GPU). The checks are shared with
the Ray tests (tests/test_ray_runner.py) through tests/loopback_cluster.py."""

import re
import time

import pytest
from loopback_cluster import (
    LoopbackCluster,
    check_cuda_steps_run_only_on_the_gpu_worker,
    check_smoke_run_with_an_s3_home,
    free_port,
    start,
    stop,
)

from capvector.flows.runtime.task_runners import RunnerConfig, runner_config


@pytest.fixture(scope="module")
def cluster(tmp_path_factory, s3_endpoint) -> LoopbackCluster:
    """A scheduler and two workers (one offering GPU=1), which reach the loopback S3 server (its
    address and keys are in their environment)."""
    from distributed import Client

    root = tmp_path_factory.mktemp("dask-cluster")
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    worker_args = ["dask", "worker", address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard"]
    scheduler = ["dask", "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"]
    procs = [start(scheduler, root, "scheduler")]
    try:
        for name, extra in (("gpu-worker", ["--resources", "GPU=1"]), ("cpu-worker", [])):
            procs.append(start([*worker_args, "--local-directory", str(root / name), *extra], root, name))
        deadline = time.monotonic() + 120
        with Client(address, timeout=120) as client:
            while len(client.scheduler_info()["workers"]) < 2:
                dead = [log for proc, log in procs if proc.poll() is not None]
                if dead or time.monotonic() > deadline:
                    pytest.fail(
                        "dask cluster did not start:\n" + "\n".join(p.read_text()[-2000:] for p in dead)
                    )
                time.sleep(0.5)
            workers = client.scheduler_info()["workers"]
        gpu = next(a for a, w in workers.items() if w.get("resources", {}).get("GPU"))
        logs = [root / "gpu-worker.log", root / "cpu-worker.log"]
        yield LoopbackCluster(
            "dask", address, gpu, lambda: _executed(address), lambda: "\n".join(f.read_text() for f in logs)
        )
    finally:
        for proc, _ in reversed(procs):
            stop(proc)


def _executed(address: str) -> dict[str, int]:
    """Tasks each worker has executed since it started."""
    from distributed import Client

    with Client(address, timeout=30) as client:
        return client.run(lambda dask_worker: dask_worker.state.executed_count)


def test_cuda_steps_run_only_on_the_gpu_worker(cluster):
    check_cuda_steps_run_only_on_the_gpu_worker(cluster, [cluster.address, cluster.address], n=4)


def test_smoke_run_with_an_s3_home_on_the_cluster(cluster, smoke_home, tmp_path):
    check_smoke_run_with_an_s3_home(cluster, smoke_home, tmp_path)


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
