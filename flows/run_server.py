"""One Prefect API server per CLI run, started first and shared by the CLI and its step workers.

Without it every process that talks to Prefect's embedded API starts its own server (the CLI and each
pool worker: three per run, ~9 s and ~250 MB each). Here the CLI starts one before it imports
Prefect, so the server boots while the CLI imports torch and the flows, and `PREFECT_API_URL` in the
environment points the CLI and every worker it spawns at that server.

The server dies with the CLI, also after `kill -9`: it is spawned from the main thread (the
parent-death signal fires when the spawning *thread* ends, and the main thread lives as long as the
process) with `PR_SET_PDEATHSIG`; a normal exit stops it after Prefect's own exit handlers have
flushed their events to it. It runs in a session of its own: Ctrl-C at the terminal (SIGINT to the
terminal's process group) reaches the CLI and its workers but not the server, so the CLI decides how
the run ends (flows.cli) instead of finding its API gone. The listening socket is bound here and
handed to uvicorn (`--fd`), so no other process can take the port between choosing it and serving on
it.

With `PREFECT_API_URL` already set (a `prefect server start`, docker-compose's server), nothing is
started: the configured server is checked for reachability instead.
"""

from __future__ import annotations

import atexit
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request

START_TIMEOUT_ENV = "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS"
PR_SET_PDEATHSIG = 1


class RunServer:
    """The run's Prefect API server process and the URL the run's processes reach it under."""

    def __init__(self) -> None:
        self._socket = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._socket.bind(("127.0.0.1", 0))
        self._socket.listen(128)
        self.port = self._socket.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}/api"
        fd = self._socket.fileno()
        # The server's own output (a start-up error; uvicorn's complaint when a failing CLI stops it
        # mid-boot) is not the user's: kept aside, and quoted if the server cannot start.
        self._output = tempfile.TemporaryFile()
        env = {
            **os.environ,
            "PREFECT_UI_ENABLED": "0",
            "PREFECT__SERVER_EPHEMERAL": "1",  # no background services, as Prefect's embedded server
            "PREFECT__SERVER_FINAL": "1",
        }
        env.pop("PREFECT_API_URL", None)
        self.process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "uvicorn",
                "--factory",
                "prefect.server.api.server:create_app",
                "--fd",
                str(fd),
                "--log-level",
                "error",
                "--lifespan",
                "on",
            ],
            env=env,
            pass_fds=(fd,),
            preexec_fn=_die_with_parent(os.getpid()),
            start_new_session=True,  # out of the terminal's process group: Ctrl-C is the CLI's to handle
            stdin=subprocess.DEVNULL,
            stdout=self._output,
            stderr=subprocess.STDOUT,
        )
        self._socket.close()  # the server holds its own copy of the listening socket

    def wait_ready(self, timeout_s: float | None = None) -> None:
        """Block until the server answers /health; its exit or the timeout is an error naming why."""
        limit = timeout_s or float(os.environ.get(START_TIMEOUT_ENV, "120"))
        deadline = time.monotonic() + limit
        while True:
            if self.process.poll() is not None:
                code = self.process.returncode
                raise RuntimeError(f"Prefect's API server exited with code {code} at start: {self._tail()}")
            try:
                urllib.request.urlopen(f"{self.url}/health", timeout=2).read()
                return
            except OSError:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"Prefect's API server did not answer within {limit:.0f} s") from None
                time.sleep(0.05)

    def _tail(self) -> str:
        self._output.seek(0)
        return " ".join(self._output.read().decode(errors="replace").split()[-60:])

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


_server: RunServer | None = None


def start_run_server() -> RunServer | None:
    """Start this run's server (once per process) unless PREFECT_API_URL names one; export its URL.

    Call before anything imports Prefect, from the main thread: Prefect reads PREFECT_API_URL when it
    is imported, and the spawning thread decides when the parent-death signal fires."""
    global _server
    if _server is not None or os.environ.get("PREFECT_API_URL"):
        return _server
    if threading.current_thread() is not threading.main_thread():
        raise RuntimeError("start the run's Prefect server from the main thread")
    _server = RunServer()
    os.environ["PREFECT_API_URL"] = _server.url
    atexit.register(_server.stop)  # registered before Prefect's handlers, so it runs after them
    return _server


def wait_for_api() -> None:
    """Before the first flow: the run's server is up, or the configured one answers."""
    if _server is not None:
        _server.wait_ready()
        return
    url = os.environ.get("PREFECT_API_URL")
    if not url:
        return
    try:
        urllib.request.urlopen(url.rstrip("/") + "/health", timeout=5).read()
    except OSError as exc:
        raise ValueError(f"the Prefect server at PREFECT_API_URL={url} is not reachable: {exc}") from None


def _die_with_parent(parent: int):
    def arm() -> None:  # runs in the child between fork and exec
        if sys.platform.startswith("linux"):
            import ctypes

            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
        if os.getppid() != parent:  # the CLI died before the signal was armed
            os._exit(1)

    return arm
