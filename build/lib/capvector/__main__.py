"""`python -m capvector …` is the `capvector` command.

It runs the CLI's module as the main module rather than this file: multiprocessing re-runs the main
module first thing in each spawned step worker, except a package's `__main__` (which it skips), and the
CLI's module is where a worker learns to leave Ctrl-C to the CLI (`leave_ctrl_c_to_the_cli`).
"""

import runpy

runpy.run_module("capvector.flows.cli.main", run_name="__main__", alter_sys=True)
