"""How pipeline steps run under Prefect: the one task decorator, and the processes a run starts.

**Results.** A step's result is an artifact id, and the content cache (capvector.tasks.runtime.caching) is the
only cache. Prefect's own cache is off and nothing is persisted to its result store: Prefect reads the
serializer named *inside* a stored result record (pickle by default, even for a record that names none), so
any record in `$PREFECT_HOME/storage` under a key a step looks up would be unpickled, i.e. run as code. A step
that its content cache answered returns `Completed(name="Cached")`, which is what Prefect's own cache hits
look like in the UI.

**Processes.** A `capvector run` starts step workers (a process pool forked from a preloaded fork server,
flows/runtime/step_pool.py) and one Prefect API server (flows/runtime/prefect_server.py) that the CLI and the
workers share. None of them may outlive the CLI, even after `kill -9`, and nothing of a dead run may commit:
- a worker asks the kernel for SIGKILL when the process that started it dies (Linux, `PR_SET_PDEATHSIG`):
  the CLI itself, or the CLI's fork server, which exits the moment the CLI is gone. So it cannot run a line
  after that; a watchdog thread (any OS) exits it when its parent changes, and a step does not start in a
  worker whose parent is gone (`RunAbandoned`);
- the server gets SIGTERM when the CLI dies (flows/runtime/prefect_server.py).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from capvector.parent_death import parent_pid, set_parent_death_signal
from capvector.tasks.runtime.caching import NotCached, probing, step_label, step_outcomes

WATCHDOG_PERIOD_S = 0.25

# The pid of the process that started this one (the CLI, or the CLI's fork server), once it is a bound
# step worker.
_bound_parent: int | None = None


class RunAbandoned(RuntimeError):
    """This worker's run is gone (its CLI died): it must not start or commit anything."""


ASCII_NAMES = str.maketrans({"θ": "theta", "γ": "gamma", "α": "alpha", "λ": "lambda", "Δ": "Delta"})
"""The Prefect UI's run graph drops these letters ("pretrain _pt"): task-run names spell them out."""


def artifact_key(text: str) -> str:
    """A Prefect artifact key (lowercase ASCII letters, digits and dashes) from a step or report name."""
    spelled = text.lower().translate(ASCII_NAMES)
    cleaned = "".join(c if c.isascii() and c.isalnum() else "-" for c in spelled)
    return "-".join(part for part in cleaned.split("-") if part)[:100] or "capvector"


def _task_run_name() -> str:
    from prefect.runtime import task_run

    return str(task_run.parameters.get("step", task_run.task_name)).translate(ASCII_NAMES)


class PipelineTask:
    """A pipeline step: its content-cache probe (`cached_id`) and, built on first use, its Prefect task.

    Prefect is imported only when a step is run or submitted, so a command that the content cache
    answers whole never imports it (about 0.8 s of a warm run). Everything else a Prefect task has is
    the Prefect task's own (`submit`, `with_options`, `fn`, ...)."""

    def __init__(self, name: str, body: Callable[..., str], retries: int, content_cached: bool):
        self.name, self.body, self.retries, self.content_cached = name, body, retries, content_cached
        self.fn = _step_runner(body)  # what the Prefect task runs (as a Prefect task's `fn` is)
        self._prefect: Any = None

    def cached_id(self, home: str, step: str, inputs: dict[str, str], config: dict[str, Any]) -> str | None:
        """The step's artifact id when the content cache holds it, else None; computes nothing."""
        if not self.content_cached:
            return None
        try:
            with probing(), step_label(step):
                return self.body(home, step, inputs, config)
        except NotCached:
            return None

    @property
    def prefect(self) -> Any:
        if self._prefect is None:
            from prefect import task
            from prefect.cache_policies import NO_CACHE

            self._prefect = task(
                name=self.name,
                cache_policy=NO_CACHE,
                persist_result=False,
                result_serializer="json",  # should results ever be persisted: JSON strings, not pickles
                task_run_name=_task_run_name,
                retries=self.retries,
            )(self.fn)
        return self._prefect

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self.prefect(*args, **kwargs)

    def __getattr__(self, attribute: str) -> Any:
        if attribute.startswith("__") or attribute == "_prefect":
            raise AttributeError(attribute)
        return getattr(self.prefect, attribute)

    def __reduce__(self) -> tuple:
        return (PipelineTask, (self.name, self.body, self.retries, self.content_cached))


def _step_runner(body: Callable[..., str]) -> Callable[..., Any]:
    """What a step's Prefect task runs: `body`, named in its errors, `Cached` when the cache answered."""

    @functools.wraps(body)
    def run_step(home: str, step: str, inputs: dict[str, str], config: dict[str, Any]) -> Any:
        from prefect.states import Completed

        refuse_if_abandoned(step)
        try:
            with step_outcomes() as outcomes, step_label(step):
                artifact_id = body(home, step, inputs, config)
        except Exception as exc:
            exc.add_note(f"in step {step!r}")  # the CLI's one-line error names the step
            raise
        if outcomes and all(outcome == "cached" for outcome in outcomes):
            return Completed(name="Cached", data=artifact_id, message=f"content cache: {artifact_id}")
        return artifact_id

    return run_step


def pipeline_task(
    name: str, retries: int = 0, content_cached: bool = True
) -> Callable[[Callable[..., Any]], PipelineTask]:
    """A Prefect task `(home, step, inputs, config) -> artifact id`, cached on content.

    The task-run name is the step label, so the UI reads like the recipe; tensors never travel
    through Prefect. A step whose artifact came from the content cache finishes as `Cached`.
    `content_cached=False`: a step that always runs (re-evaluation), so `cached_id` never asks it.
    """

    def decorate(fn: Callable[..., str]) -> PipelineTask:
        return PipelineTask(name, fn, retries, content_cached)

    return decorate


# ---------------------------------------------------------------------------- step workers
def bind_worker_to_parent() -> None:
    """Initializer of each process-pool worker: die with the process that started it.

    Runs first thing in the worker. multiprocessing's record of the parent is the CLI, whichever start
    method; the process that started the worker (getppid()) is the CLI under spawn and the CLI's fork
    server under forkserver, a child of the CLI that exits when the CLI does. The worker is bound to that
    starter, once it is known to be the CLI or its child: getppid() names init (or a subreaper) already if
    the starter died before this line. The kernel sends the parent-death signal when the *thread* that
    started the worker ends: a fork server forks from its only thread; under spawn, Prefect's process
    pool spawns workers from its resolver threads, which live until the pool has shut its workers down."""
    import multiprocessing

    global _bound_parent
    with contextlib.suppress(ValueError):  # Ctrl-C is the CLI's: it stops its workers (process_tree)
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    parent = multiprocessing.parent_process()
    if parent is None or parent.pid is None:
        return
    starter = os.getppid()
    set_parent_death_signal(signal.SIGKILL)
    if os.getppid() != starter or not _started_for(starter, parent.pid):  # gone before the signal was armed
        os._exit(1)
    _bound_parent = starter
    _start_watchdog(starter)
    quiet_failed_run_logs()


def _started_for(starter: int, cli: int) -> bool:
    """Whether `starter` is the CLI or a child of it (its fork server). Where /proc is missing, the
    starter is taken on trust (the watchdog still ends the worker when it goes)."""
    if starter == cli:
        return True
    parent = parent_pid(starter)
    return parent == cli if parent is not None else not sys.platform.startswith("linux")


# ---------------------------------------------------------------------------- failure logs
DEBUG_ENV = "CAPVECTOR_DEBUG"  # set by the CLI's --debug; step workers inherit it


class _QuietFailedRuns(logging.Filter):
    """On the console, drop Prefect's ERROR records of a failing flow or task run (its traceback, its
    "Finished in state Failed" line): the CLI prints that error itself, once, in one line. Records
    still reach Prefect's API handler (the UI keeps them)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno < logging.ERROR or not record.name.startswith(
            ("prefect.flow_runs", "prefect.task_runs")
        )


def quiet_failed_run_logs() -> None:
    """Install `_QuietFailedRuns` on this process's console handlers, unless CAPVECTOR_DEBUG is set.
    Called by the CLI before it starts a flow, and by each step worker (it logs its own failures)."""
    if os.environ.get(DEBUG_ENV, "").lower() not in ("", "0", "false"):
        return
    from prefect.logging.configuration import ensure_logging_setup

    ensure_logging_setup()  # Prefect's console handler on the root logger exists from here on
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.StreamHandler) and not any(
            isinstance(f, _QuietFailedRuns) for f in handler.filters
        ):
            handler.addFilter(_QuietFailedRuns())


def refuse_if_abandoned(step: str) -> None:
    """In a bound worker whose CLI is gone: raise instead of starting `step` (where no parent-death
    signal exists, the watchdog ends such a worker within WATCHDOG_PERIOD_S)."""
    if _bound_parent is not None and os.getppid() != _bound_parent:
        raise RunAbandoned(
            f"step {step!r} not run: its parent process {_bound_parent} (the CLI or its fork server) is gone"
        )


def _start_watchdog(parent: int) -> None:
    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(WATCHDOG_PERIOD_S)
        os._exit(1)

    threading.Thread(target=watch, name="capvector-parent-watchdog", daemon=True).start()
