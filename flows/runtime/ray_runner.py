"""`--runner ray`: prefect-ray's RayTaskRunner, quiet on the user's terminal and off stdout.

Imported only for that runner (prefect-ray is optional). As with Dask, what a step prints stays in its
worker's log: Ray would otherwise copy every worker's output, Prefect's INFO records included, to the
CLI's terminal (`log_to_driver`), and its own INFO lines go too. Ray's driver also prints what its
cluster reports (a worker that died, a task it retries) to `sys.stdout`, whatever `log_to_driver`
says; while the flow runs, that goes to stderr, so that stdout holds the command's result alone
(`--json`)."""

from __future__ import annotations

import contextlib
import logging
import sys
from typing import Any

from prefect_ray import RayTaskRunner

QUIET_INIT = {"log_to_driver": False, "logging_level": logging.WARNING}


class QuietRayTaskRunner(RayTaskRunner):
    """A RayTaskRunner whose driver's notices go to stderr (see the module's docstring)."""

    def __enter__(self) -> QuietRayTaskRunner:
        self._to_stderr = contextlib.redirect_stdout(sys.stderr)
        self._to_stderr.__enter__()
        try:
            return super().__enter__()
        except BaseException:
            self._to_stderr.__exit__(*sys.exc_info())
            raise

    def __exit__(self, *exc_info: Any) -> None:
        try:
            super().__exit__(*exc_info)  # ray.shutdown: the driver's listener stops
        finally:
            self._to_stderr.__exit__(*exc_info)


def ray_runner(address: str | None, workers: int) -> QuietRayTaskRunner:
    """Connected to the cluster at `address`, or to a local Ray of `workers` CPUs made for the run."""
    if address:
        return QuietRayTaskRunner(address=address, init_kwargs=QUIET_INIT)
    return QuietRayTaskRunner(init_kwargs={**QUIET_INIT, "num_cpus": workers})
