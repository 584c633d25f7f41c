"""How a command gets options generated from a field table (as mergekit adds its merge options from
its config model): the decorated command's own parameters, minus the one the decorator fills in, plus
the generated ones. Typer reads the resulting signature. Standard library only: `--help` stays light."""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Annotated, Any

import typer


def option_parameter(
    name: str, flag: str, kind: Any, default: Any, help: str, panel: str
) -> inspect.Parameter:
    """One keyword-only CLI option, `flag`, passed to the command as `name`."""
    option = typer.Option(flag, help=help, rich_help_panel=panel)
    return inspect.Parameter(
        name, inspect.Parameter.KEYWORD_ONLY, default=default, annotation=Annotated[kind, option]
    )


def splice_signature(
    wrapper: Callable[..., Any], command: Callable[..., Any], filled: str, extra: list[inspect.Parameter]
) -> Callable[..., Any]:
    """`wrapper` takes `command`'s parameters except `filled` (the decorator supplies it) and `extra`."""
    own = [p for p in inspect.signature(command, eval_str=True).parameters.values() if p.name != filled]
    wrapper.__signature__ = inspect.Signature([*own, *extra])
    wrapper.__annotations__ = {p.name: p.annotation for p in wrapper.__signature__.parameters.values()}
    return wrapper
