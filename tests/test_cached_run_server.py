"""A run the content cache answers whole starts no Prefect API server (issue 22, "know before you
start"): the CLI reserves the server's address before Prefect is imported, but spawns the process only
once a flow is going to run. A run with steps to do has its one server (tests/test_process_lifecycle).
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import REPO, own_server_env
from test_process_lifecycle import _tree

pytestmark = pytest.mark.skipif(
    not Path("/proc/self/stat").exists(), reason="reads the process tree in /proc"
)


def test_a_fully_cached_run_starts_no_prefect_server(smoke_home, tmp_path):
    home, ids = smoke_home
    env = own_server_env({**os.environ, "CAPVECTOR_HOME": str(home), "CAPVECTOR_QUIET": "1"})
    out = tmp_path / "stdout"
    with out.open("wb") as handle:
        proc = subprocess.Popen(
            [sys.executable, "-m", "capvector", "run", "--preset", "smoke", "--json"],
            cwd=REPO, env=env, stdout=handle, stderr=subprocess.DEVNULL, start_new_session=True,
        )  # fmt: skip
    servers: set[int] = set()
    try:
        while proc.poll() is None:
            servers |= {p for p, (_, cmd) in _tree(proc.pid).items() if "uvicorn" in cmd}
            time.sleep(0.02)
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    assert proc.returncode == 0
    assert json.loads(out.read_text()) == ids
    assert not servers, f"a fully cached run started a Prefect server: {servers}"
