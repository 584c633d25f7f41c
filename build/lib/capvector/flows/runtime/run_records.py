"""Run bookkeeping shared by all flows: a `runs` row in the catalogue and a Markdown summary in Prefect."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from capvector.artifacts.records import RunRecord, utcnow
from capvector.tasks.runtime.prefect_task import artifact_key
from capvector.tasks.runtime.workspace import Workspace


@contextmanager
def recorded_run(workspace: Workspace, flow_name: str, parameters: dict[str, Any]) -> Iterator[None]:
    """Record the flow run as RUNNING, then COMPLETED or FAILED, whatever happens in between."""
    from prefect.runtime import flow_run  # Prefect loads only where a flow runs

    run = RunRecord(
        flow_run_id=str(flow_run.id or f"local-{utcnow().isoformat()}"),
        flow_name=flow_name,
        parameters=parameters,
        started_at=utcnow(),
    )
    workspace.api.record_run(run)
    try:
        yield
    except BaseException:
        workspace.api.record_run(run.model_copy(update={"state": "FAILED", "ended_at": utcnow()}))
        raise
    workspace.api.record_run(run.model_copy(update={"state": "COMPLETED", "ended_at": utcnow()}))


def run_name() -> str:
    """`<flow> <preset> <short id>` for the Prefect UI (not a generated "sandy-tanuki")."""
    from prefect.runtime import flow_run

    config = flow_run.parameters.get("config") or {}
    preset = config.get("name") if isinstance(config, dict) else None
    return " ".join(part for part in (flow_run.flow_name, preset, str(flow_run.id or "")[:8]) if part)


def run_tags(command: str, preset: str | None = None) -> Any:
    """Tags of a flow run (and its task runs) for the UI's filters: `capvector`, the command, the preset."""
    from prefect import tags

    return tags("capvector", command, *([preset] if preset else []))


def untagged_steps() -> Any:
    """Step (task) runs carry no tags; flow runs keep theirs (the UI filters runs by them). Prefect
    acquires a concurrency slot over the API for every tag of every task run: a round trip per step
    for limits capvector never sets, and on a long-lived Dask worker the slot service (cached per set
    of tag names) keeps the API client of the first run it served, so a second CLI run on the same
    cluster, with its own run server, failed every step (ConcurrencySlotAcquisitionError)."""
    from prefect.context import TagsContext

    return TagsContext(current_tags=set())


def publish_markdown(key: str, markdown: str, description: str) -> None:
    """A Markdown artifact in the Prefect UI (a no-op cost on the embedded API)."""
    from prefect.artifacts import create_markdown_artifact

    create_markdown_artifact(markdown=markdown, key=artifact_key(key), description=description)
