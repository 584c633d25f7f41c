"""Where and how a flow's steps run: task runners, the step pool, the Prefect server, run records."""
