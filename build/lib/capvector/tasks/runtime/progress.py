"""Progress of a run and of its long steps, on the user's terminal and in the run's log file alike.

Lines go to file descriptor 2, not through `print`: inside a Prefect task `print` becomes a run-log
record (dropped below PREFECT_LOGGING_LEVEL), which is why progress from pool workers never reached
a redirected `make run > run.log`. Every process of a run (the CLI, its step workers) appends to the
log file the CLI names in CAPVECTOR_LOG_FILE; each line is one `write` on an O_APPEND descriptor, so
lines of concurrent workers never interleave within a line. One line per tenth of a step's work:
live bars from several processes would overwrite each other.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from collections.abc import Callable

LOG_FILE_ENV = "CAPVECTOR_LOG_FILE"
QUIET_ENV = "CAPVECTOR_QUIET"

# done, total, and an optional detail such as the current loss
ProgressCallback = Callable[..., None]


def quiet() -> bool:
    return os.environ.get(QUIET_ENV, "") not in ("", "0")


def emit(line: str, always: bool = False) -> None:
    """One progress line, time-stamped, to the terminal (unless quiet; `always`: a warning, shown
    anyway), to the run's log file and, inside a Prefect flow or task run, to its logs (the UI's Logs
    tab)."""
    _to_prefect(line)
    data = f"{time.strftime('%H:%M:%S')} {line}\n".encode()
    if always or not quiet():
        try:
            os.write(2, data)
        except OSError:  # no stderr (a daemon): the log file still has it
            pass
    path = os.environ.get(LOG_FILE_ENV)
    if path:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, data)
        finally:
            os.close(fd)


def _to_prefect(line: str) -> None:
    """Send the line to the Prefect API's log of the current run, at INFO, whatever the console's level
    (PREFECT_LOGGING_LEVEL=WARNING keeps Prefect's own INFO flood off the terminal; progress is ours).
    Only where Prefect is already loaded: read-only commands never import it for this."""
    if "prefect" not in sys.modules:
        return
    from prefect.context import FlowRunContext, TaskRunContext
    from prefect.logging.loggers import PrefectLogAdapter, get_run_logger

    if TaskRunContext.get() is None and FlowRunContext.get() is None:
        return
    try:
        extra = get_run_logger().extra
    except Exception:  # no run context after all (e.g. a callback thread): the file has the line
        return
    PrefectLogAdapter(_api_logger(), extra=extra).info(line)


def _api_logger() -> logging.Logger:
    logger = logging.getLogger("capvector.progress")
    if not logger.handlers:
        from prefect.logging.handlers import APILogHandler

        logger.addHandler(APILogHandler())
        logger.setLevel(logging.INFO)
        logger.propagate = False  # the terminal already has the line
    return logger


def progress_printer(step: str, unit: str) -> ProgressCallback:
    """A callback `(done, total, detail="")` that emits a line at every tenth of `total`."""
    last = {"tenth": -1}

    def report(done: int, total: int, detail: str = "") -> None:
        tenth = (10 * done) // max(total, 1)
        if tenth != last["tenth"]:
            last["tenth"] = tenth
            emit(f"[{step}] {done}/{total} {unit}" + (f", {detail}" if detail else ""))

    return report
