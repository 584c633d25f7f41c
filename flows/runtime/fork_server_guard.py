"""Imported first by the step pool's fork server: it binds the server to the process that started it
(flows/runtime/step_pool.py). Imported anywhere else, it does nothing.

A fork server exits when every process holding the write end of its "alive" pipe has gone, and every
worker it forks holds one, as the process that started it does. So a CLI killed with `kill -9` would
leave the server running, and with it the workers, whose parent it is. Importing this module in the
server asks the kernel for SIGKILL when the starter dies (Linux, `PR_SET_PDEATHSIG`); the workers, bound
to the server (capvector.tasks.runtime.prefect_task.bind_worker_to_parent), follow it. The starter names
itself in `FORK_SERVER_PARENT_ENV`; a server whose starter is already gone exits at once.
"""

from __future__ import annotations

import os
import signal
import sys

FORK_SERVER_PARENT_ENV = "CAPVECTOR_FORK_SERVER_PARENT"
PR_SET_PDEATHSIG = 1


def _in_fork_server() -> bool:
    """Whether this import runs inside multiprocessing's fork server (its preload), and not in a process
    that merely imports this module (the CLI, through step_pool)."""
    from multiprocessing import forkserver

    frame = sys._getframe()
    while frame is not None:
        if frame.f_code is forkserver.main.__code__:
            return True
        frame = frame.f_back
    return False


def _bind_to_starter() -> None:
    starter = os.environ.get(FORK_SERVER_PARENT_ENV)
    if starter is None or not _in_fork_server():
        return
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    if os.getppid() != int(starter):  # it died before the signal was armed
        os._exit(1)


_bind_to_starter()
