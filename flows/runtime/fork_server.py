"""The step pool's fork server (multiprocessing's `forkserver`): the context the pool forks its workers
from, what the server imports before it forks any, and the guard that binds it to the process that
started it. No Prefect here, so that the server can be checked where Prefect is not installed
(benchmarks/bench_fork_server_cuda.py).

Spawned, each step worker imports torch, torch._dynamo (the first optimizer does), Meta-World, Prefect and
the step modules itself: about 4 s of CPU per worker, more than a tiny step's work. The fork server imports
them once (`PRELOAD` and every module of capvector.tasks.steps) and forks each worker from that state. It
is single-threaded and has initialised neither CUDA, OpenMP nor a GL context, which is what makes forking
it safe where forking the CLI (threads, an event loop) is not.

**Dying with the CLI.** A fork server exits when every process holding the write end of its "alive" pipe
has gone, and every worker it forks holds one, as the process that started it does. So a CLI killed with
`kill -9` would leave the server running, and with it the workers, whose parent it is. This module is the
server's one preload: there it asks the kernel for SIGKILL when the starter dies (Linux,
`PR_SET_PDEATHSIG`); the workers, bound to the server (capvector.tasks.runtime.prefect_task.
bind_worker_to_parent), follow it. The starter names itself in `FORK_SERVER_PARENT_ENV`; a server whose
starter is already gone exits at once. Then it imports the rest itself (`_preload`). Imported anywhere
else, the module binds and imports nothing.
"""

from __future__ import annotations

import multiprocessing
import os
import pkgutil
import signal
import sys
import threading
from multiprocessing import forkserver
from multiprocessing.context import BaseContext

import capvector.tasks.steps
from capvector.parent_death import set_parent_death_signal

FORK_SERVER_PARENT_ENV = "CAPVECTOR_FORK_SERVER_PARENT"

PRELOAD = ("torch._dynamo", "metaworld", "prefect.task_engine")
"""Imported by the fork server before the step modules: what every worker imports sooner or later."""


def preload_modules() -> list[str]:
    """What the server imports after this module, in order: `PRELOAD`, then every module of
    capvector.tasks.steps."""
    steps = [f"capvector.tasks.steps.{m.name}" for m in pkgutil.iter_modules(capvector.tasks.steps.__path__)]
    return [*PRELOAD, *steps]


def preloaded_fork_server() -> BaseContext:
    """multiprocessing's `forkserver` context, its server told to import the step modules first (a module
    that fails to import there is imported by the worker that needs it, and fails there with its own
    error). The server's parent-death signal is bound to the thread that starts it, so it is started
    here when this is the main thread (a flow's, in the CLI): it then lives as long as the process, for
    every pool. Elsewhere it starts with the pool's first worker, from one of the pool's input-waiting
    threads, and dies when they end, after the pool's workers. Prefect enters the task runner again
    inside each step worker, which starts nothing."""
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload([__name__])  # the rest it imports itself (`_preload`)
    if multiprocessing.parent_process() is None:  # not a step worker
        os.environ[FORK_SERVER_PARENT_ENV] = str(os.getpid())
        if threading.current_thread() is threading.main_thread():
            forkserver.ensure_running()
    return context


def _in_fork_server() -> bool:
    """Whether this import runs inside multiprocessing's fork server (its preload), and not in a process
    that merely imports this module (the CLI, through step_pool)."""
    frame = sys._getframe()
    while frame is not None:
        if frame.f_code is forkserver.main.__code__:
            return True
        frame = frame.f_back
    return False


def _bind_to_starter() -> None:
    starter = os.environ.get(FORK_SERVER_PARENT_ENV)
    if starter is None:
        return
    set_parent_death_signal(signal.SIGKILL)
    if os.getppid() != int(starter):  # it died before the signal was armed
        os._exit(1)


def _preload() -> None:
    """The server's imports. multiprocessing's own preload lets any error but ImportError end the server,
    and its pool then fails with "unexpected EOF" (seen where Meta-World's import raised for want of
    EGL); here a module that fails to import is skipped, and the worker that needs it fails with the
    module's own error."""
    for name in preload_modules():
        try:
            __import__(name)
        except Exception:  # the worker that imports it reports it
            continue


if _in_fork_server():
    _bind_to_starter()
    _preload()
