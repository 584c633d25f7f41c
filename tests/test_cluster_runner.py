"""`--runner dask --address`: the steps of a run go to an existing Dask scheduler's workers, on
loopback here (`dask scheduler` and two `dask worker` processes, one offering GPU=1: conftest's
`cluster`), and give the same artifact ids as the default process pool. A step whose config asks for
cuda runs only on the worker that offers a GPU (scheduling only: nothing here touches a GPU). The
checks are shared with the Ray tests (tests/test_ray_runner.py) through tests/loopback_cluster.py."""

import re

import pytest
from loopback_cluster import (
    LoopbackCluster,
    check_cuda_steps_run_only_on_the_gpu_worker,
    check_smoke_run_with_an_s3_home,
)

from capvector.flows.runtime.task_runners import RunnerConfig, runner_config


@pytest.fixture(scope="module")
def dask_cluster(cluster) -> LoopbackCluster:
    """conftest's Dask cluster (a scheduler, a worker offering GPU=1 and one that does not), as the
    shared checks see a cluster."""
    address, logs, gpu = cluster

    def worker_output() -> str:
        return "\n".join(f.read_text() for f in logs.values())

    return LoopbackCluster("dask", address, gpu, lambda: _executed(address), worker_output)


def _executed(address: str) -> dict[str, int]:
    """Tasks each worker has executed since it started."""
    from distributed import Client

    with Client(address, timeout=30) as client:
        return client.run(lambda dask_worker: dask_worker.state.executed_count)


def test_cuda_steps_run_only_on_the_gpu_worker(dask_cluster):
    check_cuda_steps_run_only_on_the_gpu_worker(dask_cluster, [dask_cluster.address] * 2, n=4)


def test_smoke_run_with_an_s3_home_on_the_cluster(dask_cluster, smoke_home, tmp_path):
    check_smoke_run_with_an_s3_home(dask_cluster, smoke_home, tmp_path)


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
