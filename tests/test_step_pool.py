"""The flows' process pool starts a ready step while others wait for their inputs
(capvector.flows.runtime.step_pool).

A toy flow on 2 workers: a slow step `a`, two steps that wait for `a`, then an independent step `c`,
submitted in that order as a study submits its tuning runs. `c` must start while `a` still runs. On
Prefect's stock `ProcessPoolTaskRunner` it starts only after `a` ended, because the two waiting steps
hold both of its input-resolving threads; when a Prefect release stops doing that, the second test
fails and `StepPool` can go.
"""

import json
import os
import sys
import textwrap

import pytest
from conftest import REPO, run_in_session

TOY_FLOW = textwrap.dedent(
    """
    import json
    import time

    from prefect import flow, task
    from prefect.task_runners import ProcessPoolTaskRunner

    from capvector.flows.runtime.step_pool import StepPool


    @task
    def timed(seconds: float, *inputs: dict) -> dict:
        start = time.time()
        time.sleep(seconds)
        return {"start": start, "end": time.time()}


    @flow(persist_result=False)
    def toy() -> dict:
        a = timed.submit(6.0)
        waiting = [timed.submit(0.0, a), timed.submit(0.0, a)]
        c = timed.submit(0.0)
        return {"a": a.result(), "c": c.result(), "waiting": [w.result() for w in waiting]}


    if __name__ == "__main__":
        runs = {name: toy.with_options(task_runner=runner(max_workers=2))()
                for name, runner in (("step_pool", StepPool), ("stock", ProcessPoolTaskRunner))}
        print("RESULT " + json.dumps(runs))
    """
)


@pytest.fixture(scope="module")
def times(tmp_path_factory) -> dict:
    """The toy flow's step times on StepPool and on Prefect's stock pool (one process, one API)."""
    script = tmp_path_factory.mktemp("step-pool") / "toy_flow.py"
    script.write_text(TOY_FLOW)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = run_in_session([sys.executable, str(script)], env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-4000:]
    line = next(x for x in proc.stdout.splitlines() if x.startswith("RESULT "))
    return json.loads(line.removeprefix("RESULT "))


def test_a_ready_step_starts_while_others_wait_for_their_inputs(times):
    run = times["step_pool"]
    assert run["c"]["start"] < run["a"]["end"]  # c ran beside a on the second worker
    assert all(w["start"] >= run["a"]["end"] for w in run["waiting"])  # dependencies still hold


def test_prefects_own_pool_still_blocks_the_ready_step(times):
    run = times["stock"]
    assert run["c"]["start"] >= run["a"]["end"]
