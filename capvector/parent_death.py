"""Dying with a parent process: the kernel's parent-death signal, and a process's parent from /proc.

Standard library only, so that every layer can use it: the step workers' binding
(capvector.tasks.runtime.prefect_task), the step pool's fork server (capvector.flows.runtime.fork_server)
and the run's Prefect API server (capvector.flows.runtime.prefect_server). ctypes is imported with this
module because the API server arms its signal between fork and exec, where importing is unsafe.
"""

from __future__ import annotations

import ctypes
import sys

PR_SET_PDEATHSIG = 1


def set_parent_death_signal(signum: int) -> None:
    """Ask the kernel to send `signum` to this process when the *thread* that started it ends (Linux,
    `PR_SET_PDEATHSIG`); elsewhere, or without prctl, nothing: the callers' watchdogs remain."""
    if not sys.platform.startswith("linux"):
        return
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signum), 0, 0, 0)
    except (OSError, AttributeError):
        pass


def parent_pid(pid: int) -> int | None:
    """The parent of process `pid`, from /proc; None where it cannot be read (gone, or no /proc)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            text = stat.read()
    except OSError:
        return None
    return int(text[text.rindex(")") + 2 :].split()[1])
