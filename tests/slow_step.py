"""A cached step that takes its time, run by tests/test_cache_trust.py in several processes at once:
`python -c "from tests.slow_step import main; main()" HOME LOG SECONDS` prints the step's artifact id."""

import os
import sys
import time
from pathlib import Path

from capvector.tasks.runtime.caching import cached_step
from capvector.tasks.runtime.workspace import Workspace


def produce_slowly(workspace: Workspace, log: Path, seconds: float):
    def produce(key: str) -> str:
        with open(log, "a") as handle:  # one line per computation, written as it starts
            handle.write(f"{os.getpid()}\n")
        time.sleep(seconds)
        return workspace.api.register_json({"slow": 1}, "report", "slow", config={"cache_key": key}).id

    return produce


def main() -> None:
    home, log, seconds = sys.argv[1], Path(sys.argv[2]), float(sys.argv[3])
    workspace = Workspace(home)
    produce = produce_slowly(workspace, log, seconds)
    print(cached_step(workspace, "slow", {}, {"n": 1}, produce, step="slow step"), flush=True)
