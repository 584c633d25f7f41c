"""How a flow hands its steps to Prefect, and the run's progress as "step k of N".

A step whose inputs are already known and whose artifact the content cache holds runs right in the
flow's process: still a Prefect task run (shown as `Cached` in the UI), but no pool worker is started
for it, so a run where everything is cached never pays for spawning workers (seconds each: they
import torch, Prefect and Meta-World). Any other step goes to the flow's task runner.
"""

from __future__ import annotations

import threading
from typing import Any

from prefect.futures import PrefectFuture

from flows.runners import placement
from tasks.progress import emit


def resolve(value: Any) -> Any:
    """An artifact id, from a future (waiting for it) or as it is."""
    return value.result() if isinstance(value, PrefectFuture) else value


class StepRunner:
    """Submits a flow's steps and reports each one's end as `[label k/N] step: cached|done|failed`."""

    def __init__(self, home: str, total: int, label: str):
        self.home = home
        self.total = total
        self.label = label
        self._finished = 0
        self._lock = threading.Lock()
        emit(f"[{label}] {total} steps")

    def submit(self, step_task: Any, step: str, inputs: dict[str, Any], config: dict[str, Any]) -> Any:
        """The step's artifact id (a content-cache hit, run here) or a future (run by a worker)."""
        if all(isinstance(v, str) for v in inputs.values()):
            if step_task.cached_id(self.home, step, inputs, config) is not None:
                state = step_task(self.home, step, inputs, config, return_state=True)
                artifact_id = state.result()
                self._report(step, "cached")
                return artifact_id
        with placement(config):  # what the step asks of the engine: a GPU worker for a cuda step
            future = step_task.submit(self.home, step, inputs, config)
        future.add_done_callback(lambda f: self._report(step, _outcome(f)))
        return future

    def _report(self, step: str, outcome: str) -> None:
        with self._lock:
            self._finished += 1
            emit(f"[{self.label} {self._finished}/{self.total}] {step}: {outcome}")


class NotAllCached(Exception):
    """The content cache does not answer this step: the plan has work to do."""


class CacheProbe(StepRunner):
    """Answers a plan from the content cache alone, in this process and before Prefect runs anything:
    every step is looked up as the flow submits it (its inputs are the ids looked up before it), and
    the first step the cache cannot answer raises `NotAllCached`. A plan it answers whole needs no
    server, flow run or worker: the command prints its result at once (`--dry-run` lists the steps)."""

    def __init__(self, home: str, total: int, label: str):
        self.home, self.total, self.label = home, total, label
        self._finished = 0
        self._lock = threading.Lock()
        self.answered: list[tuple[str, str]] = []  # (step, artifact id), in submission order

    def submit(self, step_task: Any, step: str, inputs: dict[str, Any], config: dict[str, Any]) -> Any:
        artifact_id = step_task.cached_id(self.home, step, inputs, config)
        if artifact_id is None:
            raise NotAllCached(step)
        self.answered.append((step, artifact_id))
        return artifact_id

    def replay(self) -> None:
        """The progress lines of a plan the cache answered whole, as a flow run would print them."""
        emit(f"[{self.label}] {self.total} steps, every one cached: answered without a flow run")
        for step, _ in self.answered:
            self._report(step, "cached")


OUTCOME_WAIT_S = 30.0


def _outcome(future: PrefectFuture) -> str:
    """How a finished step ended. Never raises: it runs as a done-callback, where an exception (a step
    whose upstream failed cannot even be resolved) would be printed as a traceback; the flow reports
    the failure itself, in one line."""
    try:
        # Records the final state, which `state` would otherwise fetch from the API (stale). The future
        # is done: a pool's answers at once; a Dask future fetches its state from the worker first
        # (callbacks run on Dask's callback thread, so waiting here blocks no step).
        future.wait(timeout=OUTCOME_WAIT_S)
        state = future.state
    except Exception:
        return "failed"
    return "cached" if state.name == "Cached" else "done" if state.is_completed() else state.name.lower()
