"""Prefect flows, schedules and the `capvector` CLI (the top of the import graph)."""

import os

# No telemetry, ever: set before Prefect is imported anywhere below this package.
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("DO_NOT_TRACK", "1")
os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
# Prefect gives its embedded API server 20 s to start; on a loaded 2-core machine (training in the
# background) that is not enough and the flow fails before any step runs.
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")
