"""Test helper: steps flagged as wanting cuda, and steps that do not, submitted through a flow's
StepRunner to a running Dask scheduler or Ray cluster; prints {step: worker that ran it} as JSON (a
Dask worker's address, a Ray node's id).

    python tests/gpu_placement_probe.py dask tcp://127.0.0.1:PORT N
    python tests/gpu_placement_probe.py ray 127.0.0.1:PORT N

Runs nothing on a GPU: each step sleeps and records where it ran. The workers import this module by
name (their PYTHONPATH holds tests/).
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any

if __name__ == "__main__":
    from capvector.flows.runtime.prefect_server import start_run_server

    start_run_server()  # the run's Prefect API server, before Prefect is imported

from capvector.tasks.runtime.prefect_task import pipeline_task  # noqa: E402


@pipeline_task("placement probe", content_cached=False)
def probe_step(home: str, step: str, inputs: dict[str, str], config: dict[str, Any]) -> str:
    time.sleep(config["sleep"])
    if config["engine"] == "dask":
        from distributed import get_worker

        return get_worker().address
    import ray

    return ray.get_runtime_context().get_node_id()


def probe(engine: str, n: int) -> dict[str, str]:
    from capvector.flows.runtime.step_submission import StepRunner, resolve

    steps = StepRunner("unused", 2 * n, "placement probe")
    futures = {}
    for i in range(n):
        for device in ("cuda:0", "cpu"):
            config = {"train": {"device": device}, "sleep": 1.0, "i": i, "engine": engine}
            futures[f"{device} {i}"] = steps.submit(probe_step, f"{device} {i}", {}, config)
    return {step: resolve(future) for step, future in futures.items()}


def main(engine: str, address: str, n: int) -> None:
    from prefect import flow

    from capvector.flows.runtime.prefect_server import wait_for_api
    from capvector.flows.runtime.run_records import run_tags
    from capvector.flows.runtime.task_runners import RunnerConfig, build_runner

    wait_for_api()

    runner = build_runner(RunnerConfig(kind=engine, address=address))
    probe_flow = flow(name="placement-probe", persist_result=False)(probe).with_options(task_runner=runner)
    with run_tags("placement-probe"):  # tagged as the CLI tags its runs
        print(json.dumps(probe_flow(engine, n)))


if __name__ == "__main__":
    from gpu_placement_probe import main as probe_main  # by name: the workers import it so too

    probe_main(sys.argv[1], sys.argv[2], int(sys.argv[3]))
