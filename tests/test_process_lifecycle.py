"""A `capvector run` has one Prefect API server, shared by its step workers; the server and the
workers die with the CLI, and nothing of a dead run commits afterwards.

`kill -9` gives the CLI no chance to clean up, so each child watches its parent: it asks the kernel
for a signal when its parent dies (Linux) and the workers also poll their parent. A worker's parent is
the CLI's fork server, which exits when the CLI does.
"""

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from conftest import REPO, own_server_env

pytestmark = pytest.mark.skipif(
    not Path("/proc/self/stat").exists(), reason="reads the process tree in /proc"
)


def _stat(pid: int) -> list[str] | None:
    """Fields of /proc/<pid>/stat after the command name (state, ppid, pgrp, session, ... starttime)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def _tree(root: int) -> dict[int, tuple[str, str]]:
    """{pid: (start time, command line)} of every live process below `root`."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").glob("[0-9]*"):
        fields = _stat(int(entry.name))
        if fields and fields[0] != "Z":
            children.setdefault(int(fields[1]), []).append(int(entry.name))
    found: dict[int, tuple[str, str]] = {}
    frontier = [root]
    while frontier:
        for pid in children.get(frontier.pop(), []):
            fields = _stat(pid)
            if fields:
                found[pid] = (fields[18], _cmdline(pid))
                frontier.append(pid)
    return found


def _alive(pid: int, started: str) -> bool:
    """The same process (pid and start time) still exists and is not a zombie."""
    fields = _stat(pid)
    return fields is not None and fields[18] == started and fields[0] != "Z"


def _committed(home: Path) -> set[str]:
    """Sidecars (the store's commit points) and step-index entries in a home."""
    store = {p.name for p in (home / "store" / "objects").glob("*/*.json")}
    index = {p.name for p in (home / "step-cache").glob("*.json")}
    return store | {f"index/{name}" for name in index}


def _wait_until(condition, limit_s: float, poll_s: float = 0.2):
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(poll_s)
    return condition()


def _environ(pid: int) -> dict[str, str]:
    try:
        raw = Path(f"/proc/{pid}/environ").read_bytes()
    except OSError:
        return {}
    return dict(item.decode(errors="replace").split("=", 1) for item in raw.split(b"\0") if b"=" in item)


def test_one_server_per_run_and_kill_9_leaves_no_process_and_commits_nothing(tmp_path):
    home = tmp_path / "home"
    env = own_server_env({**os.environ, "CAPVECTOR_HOME": str(home), "CAPVECTOR_QUIET": "1"})
    proc = subprocess.Popen(
        [sys.executable, "-m", "capvector", "run", "--preset", "smoke"],
        cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
    )  # fmt: skip
    try:

        def workers() -> dict[int, tuple[str, str]]:
            """The step workers: forked by the run's fork server, the CLI's child (its command line too)."""
            forked = {p: v for p, v in _tree(proc.pid).items() if "multiprocessing.forkserver" in v[1]}
            return {p: v for p, v in forked.items() if (_stat(p) or ["", ""])[1] != str(proc.pid)}

        up = _wait_until(lambda: proc.poll() is not None or len(workers()) >= 2, 300)
        assert proc.poll() is None, "the run ended before its workers were up"
        assert up, f"workers never came up: {_tree(proc.pid)}"
        tree = _tree(proc.pid)
        servers = [p for p, (_, cmd) in tree.items() if "uvicorn" in cmd and "prefect.server" in cmd]
        assert len(servers) == 1, f"expected one Prefect API server in the run, found {servers}: {tree}"
        urls = {_environ(p).get("PREFECT_API_URL") for p in workers()}
        assert len(urls) == 1 and None not in urls, f"the workers do not share the run's API: {urls}"

        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        committed_at_kill = _committed(home)

        all_gone = _wait_until(lambda: not [p for p, (t, _) in tree.items() if _alive(p, t)], 10)
        left = {p: cmd[:120] for p, (t, cmd) in tree.items() if _alive(p, t)}
        assert all_gone, f"processes of the run alive 10 s after kill -9 of the CLI: {left}"

        time.sleep(2)  # anything still finishing a step would have written by now
        assert _committed(home) == committed_at_kill, "a step of the killed run committed afterwards"
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


# An intermediate "CLI" whose worker must die with it: a process-pool worker bound to its parent,
# busy in a step (an idle one would notice its closed queue anyway). It prints its pid, then waits.
INTERMEDIATE = textwrap.dedent(
    """
    import multiprocessing, os, subprocess, sys, time
    from concurrent.futures import ProcessPoolExecutor
    from capvector.tasks.runtime.prefect_task import bind_worker_to_parent

    def busy(path):
        with open(path, "w") as handle:
            handle.write(str(os.getpid()))
        time.sleep(300)

    if __name__ == "__main__":
        pool = ProcessPoolExecutor(1, multiprocessing.get_context("spawn"), bind_worker_to_parent)
        pool.submit(busy, sys.argv[1])
        while not os.path.exists(sys.argv[1]) or not open(sys.argv[1]).read():
            time.sleep(0.05)
        print(open(sys.argv[1]).read(), flush=True)
        time.sleep(300)
    """
)


def test_a_bound_worker_dies_with_its_parent(tmp_path):
    script = tmp_path / "intermediate.py"
    script.write_text(INTERMEDIATE)
    proc = subprocess.Popen(
        [sys.executable, str(script), str(tmp_path / "worker.pid")],
        cwd=REPO, stdout=subprocess.PIPE, text=True, start_new_session=True,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )  # fmt: skip
    try:
        worker = int(proc.stdout.readline())
        started = {worker: _stat(worker)[18]}
        assert all(_alive(pid, t) for pid, t in started.items())
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        gone = _wait_until(lambda: not any(_alive(pid, t) for pid, t in started.items()), 10, 0.05)
        assert gone, {pid: _cmdline(pid) for pid, t in started.items() if _alive(pid, t)}
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def test_an_orphaned_worker_refuses_to_run_a_step(tmp_path, monkeypatch):
    """Were a worker to outlive its CLI (no parent-death signal outside Linux), it starts no step."""
    import capvector.tasks.runtime.prefect_task as prefect_task
    from capvector.tasks.steps.data import collect_demos_task

    monkeypatch.setattr(prefect_task, "_bound_parent", os.getpid())  # we are not our own parent
    with pytest.raises(prefect_task.RunAbandoned, match="parent"):
        collect_demos_task.fn(str(tmp_path / "home"), "demos", {}, {})
    assert not (tmp_path / "home").exists()
