"""One Prefect API server per CLI run, shared by the CLI and its step workers, started only when a
flow is going to run.

Without it every process that talks to Prefect's embedded API starts its own server (the CLI and each
pool worker: three per run, ~9 s and ~250 MB each). Here the CLI reserves the server's address first
(`start_run_server`: a socket bound to a free port, `PREFECT_API_URL` exported), before it imports
Prefect, which reads that URL at import; every worker it spawns inherits it. The server process itself
is spawned when a flow is about to run (`wait_for_api`, from the command's preflight), so a command the
content cache answers whole never pays for one. `start_server_now` spawns it at once, for a command
that certainly runs a flow: it then boots while the CLI imports torch and the flows.

The server dies with the CLI, also after `kill -9`: it is spawned from the main thread (the
parent-death signal fires when the spawning *thread* ends, and the main thread lives as long as the
process) with `PR_SET_PDEATHSIG`; a normal exit stops it after Prefect's own exit handlers have
flushed their events to it. It runs in a session of its own: Ctrl-C at the terminal (SIGINT to the
terminal's process group) reaches the CLI and its workers but not the server, so the CLI decides how
the run ends (capvector.flows.cli.main) instead of finding its API gone. The server's socket is bound at
reservation and handed to uvicorn (`--fd`), so no other process can take the port between choosing it and
serving on it; it listens only once uvicorn serves, so a client that comes too early (before `wait_for_api`)
is refused at once instead of waiting on a server that may never start.

With `PREFECT_API_URL` already set (a `prefect server start`, docker-compose's server), nothing is
started: the configured server is checked for reachability instead.
"""

from __future__ import annotations

import atexit
import fcntl
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

from capvector.durable import write_atomic
from capvector.parent_death import set_parent_death_signal

START_TIMEOUT_ENV = "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS"


class RunServer:
    """The run's Prefect API server process and the URL the run's processes reach it under."""

    def __init__(self) -> None:
        self._socket: socket.socket | None = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._socket.bind(("127.0.0.1", 0))  # uvicorn listens on it once it serves
        self.port = self._socket.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}/api"
        self.process: subprocess.Popen | None = None
        self._boot_lock: int | None = None
        # The server's own output (a start-up error; uvicorn's complaint when a failing CLI stops it
        # mid-boot) is not the user's: kept aside, and quoted if the server cannot start.
        self._output = tempfile.TemporaryFile()

    def start(self) -> None:
        """Spawn the server on the reserved socket (once; from the main thread)."""
        if self.process is not None:
            return
        if threading.current_thread() is not threading.main_thread():
            raise RuntimeError("start the run's Prefect server from the main thread")
        assert self._socket is not None
        fd = self._socket.fileno()
        env = {
            **os.environ,
            "PREFECT_UI_ENABLED": "0",
            "PREFECT__SERVER_EPHEMERAL": "1",  # no background services, as Prefect's embedded server
            "PREFECT__SERVER_FINAL": "1",
        }
        env.pop("PREFECT_API_URL", None)
        self._boot_lock = _lock_prefect_home()
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
        self._release_socket()  # the server holds its own copy of the socket

    def _release_socket(self) -> None:
        if self._socket is not None:
            self._socket.close()
            self._socket = None

    def wait_ready(self, timeout_s: float | None = None) -> None:
        """Block until the server answers /health; its exit or the timeout is an error naming why."""
        self.start()
        assert self.process is not None
        limit = timeout_s or float(os.environ.get(START_TIMEOUT_ENV, "120"))
        deadline = time.monotonic() + limit
        while True:
            if self.process.poll() is not None:
                code = self.process.returncode
                raise RuntimeError(f"Prefect's API server exited with code {code} at start: {self._tail()}")
            try:
                urllib.request.urlopen(f"{self.url}/health", timeout=2).read()
                self._release_boot_lock()
                return
            except OSError:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"Prefect's API server did not answer within {limit:.0f} s") from None
                time.sleep(0.05)

    def _release_boot_lock(self) -> None:
        if self._boot_lock is not None:
            os.close(self._boot_lock)  # closing the only descriptor releases the flock
            self._boot_lock = None

    def _tail(self) -> str:
        self._output.seek(0)
        return " ".join(self._output.read().decode(errors="replace").split()[-60:])

    def stop(self) -> None:
        self._release_boot_lock()
        self._release_socket()  # never started: nothing listens on the address any more
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


_server: RunServer | None = None


def start_run_server() -> RunServer | None:
    """Reserve this run's server (once per process) unless PREFECT_API_URL names one: its port is
    bound and its URL exported, but no process starts until a flow is about to (`wait_for_api`).

    Call before anything imports Prefect: Prefect reads PREFECT_API_URL when it is imported."""
    global _server
    if _server is None and not os.environ.get("PREFECT_API_URL"):
        _server = RunServer()
        os.environ["PREFECT_API_URL"] = _server.url
        atexit.register(_server.stop)  # registered before Prefect's handlers, so it runs after them
    _no_ca_bundle_for_plain_http()
    return _server


PLAIN_HTTP_CA = "capvector-plain-http-ca.pem"


def _no_ca_bundle_for_plain_http() -> None:
    """Every Prefect client builds a verifying TLS context, also for a plain-http API that never uses
    one, and parses the whole CA bundle for it: about 40 ms of CPU per client, and a step makes two.
    For an http:// API URL (the run's own server, a local `prefect server start`) Prefect is pointed at
    a bundle of one certificate instead (PREFECT_API_SSL_CERT_FILE, unless already set), which parses in
    about 1 ms. An https:// API keeps Prefect's verification as configured."""
    plain_http = os.environ.get("PREFECT_API_URL", "").startswith("http://")
    if not plain_http or os.environ.get("PREFECT_API_SSL_CERT_FILE"):
        return
    import certifi

    bundle = _prefect_home() / PLAIN_HTTP_CA
    if not bundle.exists():
        first = Path(certifi.where()).read_text().split("-----END CERTIFICATE-----")[0]
        write_atomic(bundle, first + "-----END CERTIFICATE-----\n")
    os.environ["PREFECT_API_SSL_CERT_FILE"] = str(bundle)


def start_server_now() -> None:
    """Spawn the reserved server at once (a command that certainly runs a flow: it boots meanwhile)."""
    if _server is not None:
        _server.start()


def wait_for_api() -> None:
    """Before the first flow: the run's server is started (from the main thread) and up, or the
    configured one answers."""
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


def _prefect_home() -> Path:
    """Prefect's home folder, as Prefect resolves it (PREFECT_HOME, else ~/.prefect)."""
    return Path(os.environ.get("PREFECT_HOME") or Path.home() / ".prefect").expanduser()


def _lock_prefect_home() -> int:
    """Hold PREFECT_HOME's boot lock until the server answers: a server's start migrates and seeds
    Prefect's database, and two first starts on one new database race (a duplicate index or block
    type kills one of them). Servers of concurrent runs boot one after another; the lock is an flock,
    so a CLI that dies releases it."""
    home = _prefect_home()
    home.mkdir(parents=True, exist_ok=True)
    fd = os.open(home / ".capvector-server-boot.lock", os.O_RDWR | os.O_CREAT, 0o644)
    fcntl.flock(fd, fcntl.LOCK_EX)
    return fd


def _die_with_parent(parent: int):
    def arm() -> None:  # runs in the child between fork and exec
        set_parent_death_signal(signal.SIGTERM)
        if os.getppid() != parent:  # the CLI died before the signal was armed
            os._exit(1)

    return arm
