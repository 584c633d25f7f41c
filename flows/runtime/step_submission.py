"""How a flow hands its steps to Prefect, and the run's progress as "step k of N".

A step whose inputs are already known and whose artifact the content cache holds runs right in the
flow's process: still a Prefect task run (shown as `Cached` in the UI), but no pool worker is started
for it, so a run where everything is cached never pays for spawning workers (seconds each: they
import torch, Prefect and Meta-World). Any other step goes to the flow's task runner.

The first step to fail is recorded (`first_failure`): what the flow itself raises may be a later
step's Prefect error (`UpstreamTaskError`, `UnfinishedRun`: "Upstream task run '<uuid>' did not reach
a 'COMPLETED' state"), depending on which result it waited for first; the CLI names the step instead.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from concurrent.futures import CancelledError
from dataclasses import dataclass
from typing import Any

from capvector.flows.runtime.run_records import untagged_steps
from capvector.flows.runtime.task_runners import placement
from capvector.tasks.runtime.progress import emit


def resolve(value: Any) -> Any:
    """An artifact id, from a future (waiting for it) or as it is (no Prefect import to tell which)."""
    return value.result() if callable(getattr(value, "result", None)) else value


class StepRunner:
    """Submits a flow's steps and reports each one's end as `[label k/N] step: cached|done|failed`."""

    def __init__(self, home: str, total: int, label: str, after_gate: int = 0):
        """`total`: the steps it will submit; with a gate, those up to it (`after_gate` more follow
        only if it passes, and are added to the total then: `capvector.flows.study.plan.after_gate`)."""
        self.home = home
        self.total = total
        self.label = label
        self._finished = 0
        self._lock = threading.Lock()
        gated = f" before the gate, {after_gate} after it if the gate passes" if after_gate else ""
        emit(f"[{label}] {total} steps{gated}")

    def submit(self, step_task: Any, step: str, inputs: dict[str, Any], config: dict[str, Any]) -> Any:
        """The step's artifact id (a content-cache hit, run here) or a future (run by a worker)."""
        if all(isinstance(v, str) for v in inputs.values()):
            if step_task.cached_id(self.home, step, inputs, config) is not None:
                with untagged_steps():
                    state = step_task(self.home, step, inputs, config, return_state=True)
                try:
                    artifact_id = state.result()
                except Exception as exc:
                    record_failure(step, exc)
                    raise
                self._adopt(step, artifact_id)
                self._report(step, "cached")
                return artifact_id
        with untagged_steps(), placement(config):  # a cuda step asks the engine for a GPU worker
            future = step_task.submit(self.home, step, inputs, config)
        future.add_done_callback(lambda f: self._on_done(step, f))
        return future

    def _on_done(self, step: str, future: Any) -> None:
        outcome, error = _outcome(future)
        if error is not None:
            record_failure(step, error)  # before the progress line: the flow may be failing already
        elif outcome in ("done", "cached"):
            self._adopt(step, future)
        self._report(step, outcome)

    def _adopt(self, step: str, result: Any) -> None:
        """A remote home: index the step's artifact (`result`: its id, or its finished future) and the
        ancestors it names that this process's catalogue lacks, from their sidecars
        (`ArtifactsAPI.adopt`, no listing). A worker on another machine wrote its rows only in that
        machine's catalogue (its local cache); the driver writes those its own queries need. A local
        home's workers write the home's one catalogue: nothing to do. Never raises (a done-callback):
        a failure is one warning line, and the driver's next catch-up lists the store instead."""
        from capvector.artifacts.home import is_local

        if is_local(self.home):
            return
        try:
            from capvector.tasks.runtime.workspace import workspace_for

            artifact_id = result if isinstance(result, str) else result.result(timeout=OUTCOME_WAIT_S)
            workspace_for(self.home).api.adopt([artifact_id])
        except Exception as exc:
            emit(f"warning: step {step!r}: its artifact was not indexed here ({exc})", always=True)

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
        self.total = len(self.answered)  # a gate that did not pass stops the study short of its plan
        emit(f"[{self.label}] {self.total} steps, every one cached: answered without a flow run")
        for step, _ in self.answered:
            self._report(step, "cached")


@dataclass(frozen=True)
class PlannedStep:
    """A step of a plan that was recorded, not run: where an artifact id would be."""

    step: str
    task: str
    inputs: tuple[str, ...]
    config: dict[str, Any]


class PlanRecorder:
    """Records the steps a flow submits, in order, without running or looking up any: the plan."""

    def __init__(self) -> None:
        self.plan: list[PlannedStep] = []

    def submit(
        self, step_task: Any, step: str, inputs: dict[str, Any], config: dict[str, Any]
    ) -> PlannedStep:
        planned = PlannedStep(step, step_task.name, tuple(inputs), config)
        self.plan.append(planned)
        return planned


def record_plan(submit_all: Callable[[PlanRecorder], Any]) -> list[PlannedStep]:
    """The plan of a flow body that only submits steps and resolves their results."""
    recorder = PlanRecorder()
    submit_all(recorder)
    return recorder.plan


OUTCOME_WAIT_S = 30.0


NOT_RUN = "not run (a step it needs failed)"


def _outcome(future: Any) -> tuple[str, BaseException | None]:
    """How a finished step ended, and the step's own error if it failed. Never raises: it runs as a
    done-callback, where an exception would be printed as a traceback; the CLI reports the failure
    itself, in one line. A step that never ran because a step it needs failed has no error of its own
    (a pool cannot even resolve its inputs: its future raises `UpstreamTaskError`; a thread runner's
    task ends `NotReady`)."""
    try:
        # Records the final state, which `state` would otherwise fetch from the API (stale). The future
        # is done: a pool's answers at once; a Dask future fetches its state from the worker first
        # (callbacks run on Dask's callback thread, so waiting here blocks no step).
        future.wait(timeout=OUTCOME_WAIT_S)
        state = future.state
    except (CancelledError, asyncio.CancelledError):  # the flow stopped before the step ran
        return "cancelled", None
    except Exception as exc:
        return (NOT_RUN, None) if upstream_failed(exc) else ("failed", exc)
    if state.is_completed():
        return ("cached" if state.name == "Cached" else "done"), None
    if state.name == "NotReady":
        return NOT_RUN, None
    if not (state.is_failed() or state.is_crashed()):
        return state.name.lower(), None
    try:
        error = state.result(raise_on_failure=False)
    except Exception as exc:  # a result that cannot be read back is still this step's failure
        error = exc
    if not isinstance(error, BaseException):
        error = RuntimeError(state.message or f"the step ended {state.name}")
    return "failed", error


def upstream_failed(exc: BaseException) -> bool:
    """The error says only that a step's inputs never came (Prefect's `UpstreamTaskError`, or the
    `UnfinishedRun` of a result that never came), not why: the first failure says that."""
    from prefect.exceptions import UnfinishedRun, UpstreamTaskError

    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        if isinstance(current, UpstreamTaskError | UnfinishedRun):
            return True
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return False


@dataclass(frozen=True)
class StepFailure:
    """A step that failed, and its error."""

    step: str
    error: BaseException


_first_failure: StepFailure | None = None
_failure_lock = threading.Lock()
_failed = threading.Event()


def record_failure(step: str, error: BaseException) -> None:
    """Keep the first step failure of this process (the CLI runs one flow at a time)."""
    global _first_failure
    with _failure_lock:
        if _first_failure is None:
            _first_failure = StepFailure(step, error)
            _failed.set()


def first_failure(wait_s: float = 0.0) -> StepFailure | None:
    """The first step that failed in this process, if any; waiting up to `wait_s` for one (a step's
    done-callback may still be on its way when a later step's error has already ended the flow)."""
    if wait_s > 0:
        _failed.wait(wait_s)
    return _first_failure
