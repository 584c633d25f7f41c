"""Ctrl-C during `capvector run` ends it within seconds: one line (`interrupted`), exit 130, no process
of the run left, nothing committed afterwards, a home that verifies.

Ctrl-C at a terminal is SIGINT to the terminal's whole process group: here the run is started in a
session of its own and the signal goes to that group (os.killpg), CLI and step workers alike. The run's
Prefect API server is in a group of its own, so it is still serving when the CLI stops; it used to be
killed first, and the CLI then retried its events for minutes, printing ~84 lines, and exited 1.
"""

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import REPO, own_server_env, run_cli
from test_process_lifecycle import _alive, _committed, _stat, _tree, _wait_until

pytestmark = pytest.mark.skipif(
    not Path("/proc/self/stat").exists(), reason="reads the process tree in /proc"
)

TRAINING = re.compile(r"\[pretrain θ_pt\] \d+/\d+ steps")
EVALUATION = re.compile(r"\[(?:validate|test) [^\]]+\] \d+/\d+ episodes")  # a run is a study: its evaluations
EXIT_LIMIT_S = 15
MAX_LINES_AFTER = 5


def _interrupt_when(pattern: re.Pattern, tmp_path: Path) -> None:
    home = tmp_path / "home"
    env = {**os.environ, "CAPVECTOR_HOME": str(home), "PREFECT_HOME": str(tmp_path / "prefect")}
    env = own_server_env(env)
    env.pop("CAPVECTOR_QUIET", None)  # the progress lines say where the run is
    err_path = tmp_path / "stderr"
    with err_path.open("wb") as err, (tmp_path / "stdout").open("wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "capvector", "run", "--preset", "smoke"],
            cwd=REPO, env=env, stdout=out, stderr=err, start_new_session=True,
        )  # fmt: skip
    try:
        reached = _wait_until(
            lambda: proc.poll() is not None or pattern.search(err_path.read_text(errors="replace")), 300, 0.05
        )
        text = err_path.read_text(errors="replace")
        assert proc.poll() is None and reached, f"the run ended before {pattern.pattern}:\n{text[-3000:]}"
        tree = _tree(proc.pid)
        servers = [p for p, (_, cmd) in tree.items() if "uvicorn" in cmd and "prefect.server" in cmd]
        assert len(servers) == 1, tree
        assert _stat(servers[0])[2] != str(proc.pid), "the API server is in the terminal's process group"
        seen = len(text)

        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C
        start = time.monotonic()
        try:
            code = proc.wait(timeout=EXIT_LIMIT_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"still running {EXIT_LIMIT_S} s after Ctrl-C:\n{err_path.read_text()[-3000:]}")
        took = time.monotonic() - start
        committed_at_exit = _committed(home)

        tree.update(_tree(proc.pid))
        gone = _wait_until(lambda: not [p for p, (t, _) in tree.items() if _alive(p, t)], 10)
        left = {p: cmd[:120] for p, (t, cmd) in tree.items() if _alive(p, t)}
        assert gone, f"processes of the run alive 10 s after it exited: {left}"
        time.sleep(1)  # a step still finishing would have committed by now
        after = [line for line in err_path.read_text(errors="replace")[seen:].splitlines() if line.strip()]
        assert code == 130, (code, after)
        assert after and after[-1] == "interrupted", after
        assert len(after) < MAX_LINES_AFTER, after
        assert (tmp_path / "stdout").read_text() == ""
        assert took < 5, f"{took:.1f} s from Ctrl-C to exit"
        assert _committed(home) == committed_at_exit, "a step of the interrupted run committed afterwards"
        logs = list((home / "logs").glob("run-smoke-*.log"))
        assert len(logs) == 1 and logs[0].read_text().rstrip().endswith("interrupted (Ctrl-C)"), logs
        run_cli("verify", "--all", home=home)  # what was committed is whole
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def test_ctrl_c_during_training_ends_the_run_in_seconds_with_one_line(tmp_path):
    _interrupt_when(TRAINING, tmp_path)


def test_ctrl_c_during_evaluation_ends_the_run_in_seconds_with_one_line(tmp_path):
    _interrupt_when(EVALUATION, tmp_path)


BUSY_FLOW = """
import subprocess, sys, time
from capvector.flows.cli.process_tree import stop_on_signals
stop_on_signals()
helper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
from prefect.utilities.engine import capture_sigterm
with capture_sigterm():  # what Prefect's flow engine installs while a flow runs
    print(helper.pid, flush=True)
    end = time.monotonic() + 40
    while time.monotonic() < end:  # an engine tearing down thousands of planned steps, catching all
        try:
            time.sleep(0.01)
        except BaseException:
            pass
"""


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_stops_the_cli_whatever_its_main_thread_is_doing(signum, tmp_path):
    """SIGTERM to `capvector study` on a plan of 8,879 steps left the CLI running 12 s (9,800 steps: over
    30 s): Prefect's SIGTERM handler, swapped in while a flow runs, raised inside the flow, whose teardown
    went on cancelling and failing planned steps (and printing them) before the signal reached ours. The
    signal is now acted on by a thread of its own from the wakeup pipe: exit 128 + signal, helpers gone."""
    err = (tmp_path / "err").open("w+")
    proc = subprocess.Popen(
        [sys.executable, "-c", BUSY_FLOW], cwd=REPO, stdout=subprocess.PIPE, stderr=err, text=True,
        start_new_session=True,
    )  # fmt: skip
    try:
        helper = int(proc.stdout.readline())
        started = _stat(helper)[18]
        os.kill(proc.pid, signum)
        start = time.monotonic()
        try:
            code = proc.wait(timeout=EXIT_LIMIT_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"still running {EXIT_LIMIT_S} s after {signum.name}")
        took = time.monotonic() - start
        err.seek(0)
        assert code == 128 + signum, (code, err.read()[-2000:])
        assert took < 3, f"{took:.1f} s from {signum.name} to exit"
        assert _wait_until(lambda: not _alive(helper, started), 5), "the helper outlived the CLI"
    finally:
        os.killpg(proc.pid, signal.SIGKILL) if proc.poll() is None else None
