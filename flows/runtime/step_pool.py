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

Its workers are forked from a preloaded fork server (flows/runtime/fork_server.py) instead of spawned:
the step modules and their libraries are imported once per process, not once per worker, and the server
dies with the process that started it, the workers with it. benchmarks/results/pipeline.md has a cold
run's CPU with both start methods.
"""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from typing import Self

from prefect.task_runners import ProcessPoolTaskRunner, _initialize_process_pool_worker

from capvector.flows.runtime.fork_server import preloaded_fork_server
from capvector.tasks.runtime.prefect_task import bind_worker_to_parent

WAITING_STEPS = 512
"""Steps that may wait for their inputs at once (a large study submits a few hundred)."""


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
