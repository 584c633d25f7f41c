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
        future = step_task.submit(self.home, step, inputs, config)
        future.add_done_callback(lambda f: self._report(step, _outcome(f)))
        return future

    def _report(self, step: str, outcome: str) -> None:
        with self._lock:
            self._finished += 1
            emit(f"[{self.label} {self._finished}/{self.total}] {step}: {outcome}")


def _outcome(future: PrefectFuture) -> str:
    """How a finished step ended. Never raises: it runs as a done-callback, where an exception (a step
    whose upstream failed cannot even be resolved) would be printed as a traceback; the flow reports
    the failure itself, in one line."""
    try:
        future.wait(timeout=0)  # records the final state, which `state` would otherwise fetch (stale)
        state = future.state
    except Exception:
        return "failed"
    return "cached" if state.name == "Cached" else "done" if state.is_completed() else state.name.lower()
