"""Test helper: steps flagged as wanting cuda, and steps that do not, submitted through a flow's
StepRunner to a running Dask scheduler; prints {step: address of the worker that ran it} as JSON.

    python tests/gpu_placement_probe.py tcp://127.0.0.1:PORT N

Runs nothing on a GPU: each step sleeps and records `distributed.get_worker().address`. The Dask
workers import this module by name (their PYTHONPATH holds tests/).
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
    from distributed import get_worker

    time.sleep(config["sleep"])
    return get_worker().address


def probe(n: int) -> dict[str, str]:
    from capvector.flows.runtime.step_submission import StepRunner, resolve

    steps = StepRunner("unused", 2 * n, "placement probe")
    futures = {}
    for i in range(n):
        for device in ("cuda:0", "cpu"):
            config = {"train": {"device": device}, "sleep": 1.0, "i": i}
            futures[f"{device} {i}"] = steps.submit(probe_step, f"{device} {i}", {}, config)
    return {step: resolve(future) for step, future in futures.items()}


def main(address: str, n: int) -> None:
    from prefect import flow

    from capvector.flows.runtime.prefect_server import wait_for_api
    from capvector.flows.runtime.run_records import run_tags
    from capvector.flows.runtime.task_runners import RunnerConfig, build_runner

    wait_for_api()

    runner = build_runner(RunnerConfig(kind="dask", address=address))
    probe_flow = flow(name="placement-probe", persist_result=False)(probe).with_options(task_runner=runner)
    with run_tags("placement-probe"):  # tagged as the CLI tags its runs
        print(json.dumps(probe_flow(n)))


if __name__ == "__main__":
    from gpu_placement_probe import main as probe_main  # by name: the workers import it so too

    probe_main(sys.argv[1], int(sys.argv[2]))
