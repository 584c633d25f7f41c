"""A cached step that takes its time, run by tests/test_cache_trust.py in several processes at once:
`python -c "from tests.slow_step import main; main()" HOME LOG HOLD` prints the step's artifact id. HOLD is
how long the computation takes: seconds, or `until=PATH`, until that file exists (at most 300 s)."""

import os
import sys
import time
from pathlib import Path

from capvector.tasks.runtime.caching import cached_step
from capvector.tasks.runtime.workspace import Workspace


def produce_slowly(workspace: Workspace, log: Path, hold: str):
    def produce(key: str) -> str:
        with open(log, "a") as handle:  # one line per computation, written as it starts
            handle.write(f"{os.getpid()}\n")
        if hold.startswith("until="):
            deadline = time.monotonic() + 300
            while not Path(hold.removeprefix("until=")).exists() and time.monotonic() < deadline:
                time.sleep(0.05)
        else:
            time.sleep(float(hold))
        return workspace.api.register_json({"slow": 1}, "report", "slow", config={"cache_key": key}).id

    return produce


def main() -> None:
    home, log, hold = sys.argv[1], Path(sys.argv[2]), sys.argv[3]
    workspace = Workspace(home)
    produce = produce_slowly(workspace, log, hold)
    print(cached_step(workspace, "slow", {}, {"n": 1}, produce, step="slow step"), flush=True)
