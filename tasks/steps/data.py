"""Step: collect expert demonstrations on Meta-World and store them as a dataset artifact."""

from __future__ import annotations

from typing import Any

from capvector.core.simulation.demos import DemoConfig, collect_demos
from capvector.tasks.runtime.caching import cached_step
from capvector.tasks.runtime.prefect_task import pipeline_task
from capvector.tasks.runtime.progress import progress_printer
from capvector.tasks.runtime.workspace import Workspace, provenance, workspace_for


def run_collect_demos(workspace: Workspace, step: str, config: dict[str, Any]) -> str:
    demo_config = DemoConfig.model_validate(config)

    def produce(key: str) -> str:
        dataset = collect_demos(demo_config, progress=progress_printer(step, "episodes"))
        with workspace.scratch() as tmp:
            path = dataset.save(tmp / "dataset")
            record = workspace.api.register_dir(
                path,
                kind="dataset",
                name=step,
                config={
                    "demo": demo_config.model_dump(),
                    "cache_key": key,
                    "failures": dataset.meta.failures,
                    "n_steps": dataset.meta.n_steps,
                },
                **provenance(),
            )
        return record.id

    return cached_step(workspace, "collect_demos", {}, demo_config, produce)


@pipeline_task("collect_demos")
def collect_demos_task(home: str, step: str, inputs: dict[str, str], config: dict[str, Any]) -> str:
    return run_collect_demos(workspace_for(home), step, config)
