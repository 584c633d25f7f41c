"""Scheduled re-evaluation: the `reevaluate` flow as a Prefect deployment with a cron, served."""

from __future__ import annotations

from typing import Any

from capvector.flows.evaluation.flow import DEFAULT_SELECTION, reevaluate_flow


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


def serve_deployment(deployment: Any) -> None:
    from prefect import serve

    from capvector.flows.runtime.prefect_server import wait_for_api

    wait_for_api()
    serve(deployment)
