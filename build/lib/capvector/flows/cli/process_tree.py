"""The CLI's helpers die with it: Ctrl-C and SIGTERM stop the step workers and the run's server, say
`interrupted` and exit 128 + signal, without flushing anything (every step commits atomically)."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any


def descendant_pids(root: int) -> list[int]:
    """Every live process below `root` (from /proc; empty where there is none, e.g. macOS)."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, ValueError, IndexError):
            fields = stat.read_text().rsplit(")", 1)[1].split()
            children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, frontier = [], [root]
    while frontier:
        kids = children.get(frontier.pop(), [])
        found += kids
        frontier += kids
    return found


def stop_descendants() -> None:
    for pid in descendant_pids(os.getpid()):
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, signal.SIGTERM)


def leave_ctrl_c_to_the_cli() -> None:
    """In a step worker, ignore SIGINT: the CLI stops its workers on Ctrl-C (`stop_on_signals`), and a
    worker taking the terminal's SIGINT itself would print a KeyboardInterrupt traceback. A spawned
    worker runs the CLI's main module first thing (`capvector/__main__.py` as its `__mp_main__`, or the
    console script through `capvector.flows.cli.main`), which calls this before importing anything
    heavy, so the worker ignores Ctrl-C from its first moments. Costs the CLI nothing: it only looks at
    modules already loaded."""
    mp = sys.modules.get("multiprocessing")
    if mp is not None and mp.current_process().name != "MainProcess":
        with contextlib.suppress(ValueError):  # not imported from a main thread: leave it
            signal.signal(signal.SIGINT, signal.SIG_IGN)


def stop_on_signals() -> Callable[[], bool]:
    """Ctrl-C (SIGINT) and SIGTERM end the CLI at once and take its helpers along: the step workers
    and Prefect's API server would otherwise outlive it. The workers are stopped first (SIGTERM, then
    their parent-death SIGKILL as the CLI exits), and the CLI exits without flushing anything: every
    step commits atomically, so stopping mid-step loses only that step's unfinished work, exactly as a
    SIGKILL would, and Prefect's pending events (run states, logs for the UI) are dropped with the
    server that would have taken them, instead of being retried for minutes against a stopped one.
    The server is out of the terminal's process group (capvector.flows.runtime.prefect_server), so Ctrl-C
    reaches only the CLI and its workers and the CLI says how the run ended: `interrupted`, exit 130 (143 on
    SIGTERM).

    While a flow runs Prefect swaps in its own SIGTERM handler, which raises inside whatever is running:
    a DuckDB call turned that into "Query interrupted" and the signal was lost, and the flow engine's
    teardown of a large plan (cancelling and failing thousands of planned steps) kept the CLI and its
    workers running for 30 s and more before the signal reached this handler. So every signal is also
    recorded below Python's handlers (the wakeup pipe), and a thread of its own acts on SIGINT and
    SIGTERM at once, whatever the main thread is doing or whoever's handler is installed. The returned
    `terminated()` says whether SIGTERM came."""

    def stop(signum: int, _frame: Any) -> None:
        end(signum)

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    read_end, write_end = os.pipe()
    os.set_blocking(write_end, False)
    signal.set_wakeup_fd(write_end, warn_on_full_buffer=False)
    seen = threading.Event()

    def watch() -> None:
        while True:
            try:
                received = os.read(read_end, 1024)
            except InterruptedError:
                continue
            except OSError:
                return
            for signum in (signal.SIGTERM, signal.SIGINT):
                if int(signum) in received:
                    if signum == signal.SIGTERM:
                        seen.set()
                    end(signum)

    threading.Thread(target=watch, name="capvector-signals", daemon=True).start()
    return seen.is_set


_ending = threading.Lock()


def end(signum: int) -> None:
    """Stop every helper, say `interrupted` on Ctrl-C (terminal and run log), exit 128 + signum. Once:
    a second caller (the signal's Python handler and the watching thread) waits for the first's exit."""
    if not _ending.acquire(blocking=False):
        while True:
            time.sleep(60)
    stop_descendants()
    if signum == signal.SIGINT:
        with contextlib.suppress(OSError):
            os.write(2, b"interrupted\n")
        # loaded where a run log was started (no import here)
        progress = sys.modules.get("capvector.tasks.runtime.progress")
        if progress is not None and (log := os.environ.get(progress.LOG_FILE_ENV)):
            with contextlib.suppress(OSError):
                fd = os.open(log, os.O_WRONLY | os.O_APPEND)
                os.write(fd, f"{time.strftime('%H:%M:%S')} interrupted (Ctrl-C)\n".encode())
                os.close(fd)
    os._exit(128 + signum)


# multiprocessing's resource tracker (a helper process of the step pool) unlinks the pool's semaphores
# when the CLI ends without closing the pool (a signal, kill -9) and warns about them in two lines.
# Nothing is leaked after all; every process it starts gets the interpreter's -W options.
QUIET_RESOURCE_TRACKER = "ignore:resource_tracker:UserWarning:multiprocessing.resource_tracker"
