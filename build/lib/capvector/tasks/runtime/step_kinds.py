"""Pipeline steps declared once, and the one executor that runs every one of them.

A step kind (`StepKind`) says what is particular to a step: its name (the content cache's kind and
the Prefect task's name), its config model, the inputs it needs and `produce`, which computes and
registers its artifact. `StepKind.run` does what every step does around that: validate the config
and check the inputs before any cache lookup (so a wrong step fails even when only probed), then
return the content cache's artifact or produce and register one
(capvector.tasks.runtime.caching.cached_step). `step_task` makes the step's Prefect task.

The content key hashes the code of `produce`'s module (capvector.tasks.runtime.step_code): a step
declared in capvector.tasks.steps.training is keyed on that module's import closure.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel

from capvector.tasks.runtime.caching import cached_step
from capvector.tasks.runtime.prefect_task import PipelineTask
from capvector.tasks.runtime.workspace import Workspace, workspace_for


@dataclass(frozen=True)
class StepCall:
    """What `produce` works from: the step's validated config (the config as given for a kind without
    a model) and the content key to record with its artifact (None: a step that is not content-cached)."""

    workspace: Workspace
    step: str
    inputs: dict[str, str]
    config: Any
    key: str | None


@dataclass(frozen=True)
class StepKind:
    """A pipeline step's declaration.

    `inputs`: the roles it cannot run without. `check`: any further test of (step, inputs, validated
    config) that must fail before the cache is asked (inputs named by the config, settings that
    exclude each other). `key_on_model`: the key hashes the validated config without its
    ExecutionOnly fields (capvector.core.training.execution: where a step runs is no part of its
    result) instead of the config as given. `content_cached=False`: always produced, never looked up.
    """

    name: str
    config: type[BaseModel] | None
    inputs: tuple[str, ...]
    produce: Callable[[StepCall], str]
    check: Callable[[str, dict[str, str], Any], None] | None = None
    key_on_model: bool = False
    content_cached: bool = True

    def run(self, workspace: Workspace, step: str, inputs: dict[str, str], config: dict[str, Any]) -> str:
        """The step's artifact id: validate, check the inputs, then the cache's answer or `produce`'s."""
        validated = self.config.model_validate(config) if self.config is not None else config
        for role in self.inputs:
            if role not in inputs:
                raise ValueError(f"step {step!r}: {self.name} needs a {role!r} input")
        if self.check is not None:
            self.check(step, inputs, validated)

        def produce(key: str | None) -> str:
            return self.produce(StepCall(workspace, step, inputs, validated, key))

        if not self.content_cached:
            return produce(None)
        keyed = validated if self.key_on_model else config
        return cached_step(
            workspace, self.name, inputs, keyed, produce, step=step, module=self.produce.__module__
        )

    def run_in_home(self, home: str, step: str, inputs: dict[str, str], config: dict[str, Any]) -> str:
        """What the Prefect task runs: `run` on this process's workspace of `home`."""
        return self.run(workspace_for(home), step, inputs, config)


def step_task(kind: StepKind) -> PipelineTask:
    """The kind's Prefect task `(home, step, inputs, config) -> artifact id`, named after it."""
    return PipelineTask(kind.name, kind.run_in_home, retries=0, content_cached=kind.content_cached)
