"""`capvector evaluate`'s protocol options, generated from `capvector.core.evaluation.fields` (the table
`EvalConfig`'s defaults and descriptions come from): one declaration per option. The command receives
the given values as `eval_settings`, keyed by `EvalConfig` field, and validates them with the model."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

from capvector.core.evaluation.fields import EVAL_FIELDS
from capvector.flows.cli.generated_options import option_parameter, splice_signature

EVAL_PANEL = "Evaluation protocol"


def eval_options(command: Callable[..., Any]) -> Callable[..., Any]:
    """Add one option per `EVAL_FIELDS` entry to a command that takes `eval_settings`."""

    @functools.wraps(command)
    def with_protocol(*args: Any, **kwargs: Any) -> Any:
        settings = {name: kwargs.pop(name, spec.default) for name, spec in EVAL_FIELDS.items()}
        return command(*args, eval_settings=settings, **kwargs)

    options = [option_parameter(name, *spec, EVAL_PANEL) for name, spec in EVAL_FIELDS.items()]
    return splice_signature(with_protocol, command, "eval_settings", options)
