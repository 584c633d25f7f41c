"""Scheduled re-evaluation: the `reevaluate` flow as a Prefect deployment with a cron, served."""

from __future__ import annotations

from typing import Any

from flows.evaluation_flows import DEFAULT_SELECTION, reevaluate_flow


def validate_cron(cron: str) -> str:
    """Prefect's own cron schedule model decides what is valid; its error is re-raised with the field."""
    from prefect.client.schemas.schedules import CronSchedule

    try:
        CronSchedule(cron=cron)
    except Exception as exc:  # pydantic ValidationError or ValueError, depending on the input
        raise ValueError(f"invalid cron expression {cron!r}: {exc}") from None
    return cron


def build_deployment(cron: str, home: str, query: str | None, name: str) -> Any:
    validate_cron(cron)
    return reevaluate_flow.to_deployment(
        name=name, cron=cron, parameters={"home": home, "selection_sql": query or DEFAULT_SELECTION}
    )


def check_server_reachable() -> None:
    """With PREFECT_API_URL set, fail early with its address when the server does not answer."""
    import os
    import urllib.request

    url = os.environ.get("PREFECT_API_URL")
    if not url:
        return
    try:
        urllib.request.urlopen(url.rstrip("/") + "/health", timeout=5).read()
    except OSError as exc:
        raise ValueError(f"the Prefect server at PREFECT_API_URL={url} is not reachable: {exc}") from None


def serve_deployment(deployment: Any) -> None:
    from prefect import serve

    check_server_reachable()
    serve(deployment)
