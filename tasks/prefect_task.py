"""The one Prefect task decorator every pipeline step uses: content cache keys, persisted results."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from prefect import task

from tasks.caching import prefect_cache_key


def pipeline_task(name: str, retries: int = 0) -> Callable[[Callable[..., Any]], Any]:
    """A Prefect task `(home, step, inputs, config) -> artifact id`, cached on content.

    Results are artifact ids (strings): persisting them is cheap, and tensors never travel through
    Prefect. The task-run name is the step label, so the UI reads like the recipe.
    """
    return task(
        name=name,
        cache_key_fn=prefect_cache_key,
        persist_result=True,
        task_run_name="{step}",
        retries=retries,
    )
