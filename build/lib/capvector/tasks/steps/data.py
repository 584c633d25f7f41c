"""Step: collect expert demonstrations on Meta-World and store them as a dataset artifact."""

from __future__ import annotations

from capvector.core.simulation.demos import DemoConfig, collect_demos
from capvector.tasks.runtime.progress import progress_printer
from capvector.tasks.runtime.step_kinds import StepCall, StepKind, step_task
from capvector.tasks.runtime.workspace import provenance


def _collect(call: StepCall) -> str:
    dataset = collect_demos(call.config, progress=progress_printer(call.step, "episodes"))
    with call.workspace.scratch() as tmp:
        path = dataset.save(tmp / "dataset")
        record = call.workspace.api.register_dir(
            path,
            kind="dataset",
            name=call.step,
            config={
                "demo": call.config.model_dump(),
                "cache_key": call.key,
                "failures": dataset.meta.failures,
                "n_steps": dataset.meta.n_steps,
            },
            **provenance(),
        )
    return record.id


COLLECT_DEMOS = StepKind("collect_demos", DemoConfig, (), _collect, key_on_model=True)
collect_demos_task = step_task(COLLECT_DEMOS)
