"""The options that say where a flow's steps run, declared once: `capvector.flows.runtime.task_runner_fields`
holds each `capvector.flows.runtime.task_runners.RunnerConfig` field's description (the model's field
descriptions are these), and `runner_options` adds `--runner`, `--address`, `--workers`, `--cluster-class` and
`--cluster-kwargs` to every command it decorates, the way mergekit adds its merge options from its config
model. The command receives the checked `RunnerConfig` as `runner_config`; a bad value exits 2 naming the
option, before any server, flow or worker starts. No pydantic here: `--help` and `sql` stay light."""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable
from typing import Any

from capvector.flows.cli.generated_options import option_parameter, splice_signature
from capvector.flows.runtime.task_runner_fields import DEFAULT_WORKERS, RUNNER_FIELDS

RUNNER_PANEL = "Where steps run"
# option name (as the command sees it) -> (flag, RunnerConfig field, type, default)
_OPTIONS = {
    "runner": ("--runner", "kind", str | None, None),
    "address": ("--address", "address", str | None, None),
    "workers": ("--workers", "workers", int, DEFAULT_WORKERS),
    "cluster_class": ("--cluster-class", "cluster_class", str | None, None),
    "cluster_kwargs": ("--cluster-kwargs", "cluster_kwargs", str | None, None),
}


def _parameter(name: str) -> inspect.Parameter:
    flag, field, kind, default = _OPTIONS[name]
    return option_parameter(name, flag, kind, default, RUNNER_FIELDS[field], RUNNER_PANEL)


def runner_options(default: str = "process") -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Add the runner options to a command that takes `runner_config`; `default` is the runner when
    `--runner` is not given (`thread` for evaluate and reevaluate)."""

    def add(command: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(command)
        def with_runner(*args: Any, **kwargs: Any) -> Any:
            from capvector.flows.runtime.task_runners import runner_config

            given = {name: kwargs.pop(name, spec[3]) for name, spec in _OPTIONS.items()}
            kind = given["runner"] or default
            if kind == "thread" and default != "thread":
                raise ValueError(
                    "--runner thread is for evaluate and reevaluate: training steps need processes"
                )
            config = runner_config(
                kind, given["address"], given["workers"], given["cluster_class"], given["cluster_kwargs"]
            )
            return command(*args, runner_config=config, **kwargs)

        splice_signature(with_runner, command, "runner_config", [*map(_parameter, _OPTIONS)])
        return with_runner

    return add
