"""The process pool the flows run their steps on: Prefect's, minus a head-of-line block, forked from a
preloaded fork server.

Prefect's `ProcessPoolTaskRunner` waits for a submitted step's input futures on a thread pool as large
as its process pool, in submission order. A flow that submits two steps waiting for inputs before a
step whose inputs are ready therefore leaves the ready one queued, with process workers idle, until an
input arrives. In a study this serialized the tuning runs of θ_ao's auxiliary weights: the validation
and held-out-loss steps of the first run held both waiting threads, so the second run started only
when the first had finished. The same class of hang made Prefect give `ThreadPoolTaskRunner` an
unbounded pool (PrefectHQ/prefect#14194). Waiting costs a thread nothing, so `StepPool` gives each
waiting step its own (up to `WAITING_STEPS`); the process pool still runs at most `max_workers` steps
at once.

Prefect spawns each worker, and each then imports torch, torch._dynamo (the first optimizer does),
Meta-World, Prefect and the step modules: about 4 s of CPU per worker, more than a tiny step's work.
`StepPool` starts its workers from a fork server instead (multiprocessing's `forkserver`): one clean
process, started with the first pool, that imports those modules once (`PRELOAD` and every module of
capvector.tasks.steps) and forks each worker from that state. It is single-threaded and has initialised
neither CUDA, OpenMP nor a GL context, which is what makes forking it safe where forking the CLI
(threads, an event loop) is not. It dies with the process that started it
(flows/runtime/fork_server_guard.py, its first import), and the workers with it.
benchmarks/results/pipeline.md has a cold run's CPU with both start methods.
"""

from __future__ import annotations

import multiprocessing
import os
import pkgutil
import threading
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from multiprocessing import forkserver
from multiprocessing.context import BaseContext
from typing import Self

from prefect.task_runners import ProcessPoolTaskRunner, _initialize_process_pool_worker

import capvector.tasks.steps
from capvector.flows.runtime.fork_server_guard import FORK_SERVER_PARENT_ENV
from capvector.tasks.runtime.prefect_task import bind_worker_to_parent

WAITING_STEPS = 512
"""Steps that may wait for their inputs at once (a large study submits a few hundred)."""

PRELOAD = ("capvector.flows.runtime.fork_server_guard", "torch._dynamo", "metaworld", "prefect.task_engine")
"""Imported by the fork server, in this order, before the step modules: the guard that binds it to its
starter, then what every worker imports sooner or later."""


def preloaded_fork_server() -> BaseContext:
    """multiprocessing's `forkserver` context, its server told to import the step modules first (a module
    that fails to import there is imported by the worker that needs it, and fails there with its own
    error). The server's parent-death signal is bound to the thread that starts it, so it is started
    here when this is the main thread (a flow's, in the CLI): it then lives as long as the process, for
    every pool. Elsewhere it starts with the pool's first worker, from one of the pool's input-waiting
    threads, and dies when they end, after the pool's workers. Prefect enters the task runner again
    inside each step worker, which starts nothing."""
    steps = [f"capvector.tasks.steps.{m.name}" for m in pkgutil.iter_modules(capvector.tasks.steps.__path__)]
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([*PRELOAD, *steps])
    if multiprocessing.parent_process() is None:  # not a step worker
        os.environ[FORK_SERVER_PARENT_ENV] = str(os.getpid())
        if threading.current_thread() is threading.main_thread():
            forkserver.ensure_running()
    return context


class StepPool(ProcessPoolTaskRunner):
    def __enter__(self) -> Self:
        super().__enter__()
        # Prefect's executor has started no worker yet (they start on the first submit): replace it by
        # the same executor on the fork server, with Prefect's worker set-up (its log and event
        # forwarding) and our initializer as it passes them.
        self._executor.shutdown(wait=False)
        self._executor = ProcessPoolExecutor(
            max_workers=self._max_workers,
            mp_context=preloaded_fork_server(),
            initializer=_initialize_process_pool_worker,
            initargs=(self._subprocess_message_queue, self._initializer, self._initargs),
        )
        narrow = getattr(self, "_resolver_executor", None)
        if isinstance(narrow, ThreadPoolExecutor):  # prefect versions that resolve inputs in the parent
            narrow.shutdown(wait=False)
            self._resolver_executor = ThreadPoolExecutor(
                max_workers=WAITING_STEPS, thread_name_prefix="step-inputs"
            )
        return self


def step_runner(workers: int = 2) -> StepPool:
    """The flows' default runner: a pool of step processes, because steps seed torch's process-global
    RNG and must not share it, and two training steps in two processes use both cores without
    contending for the GIL. Each worker is bound to the process that started it
    (capvector.tasks.runtime.prefect_task.bind_worker_to_parent): a killed CLI takes its workers, and
    their embedded API servers, along."""
    return StepPool(max_workers=workers, initializer=bind_worker_to_parent)
