"""What the CLI's command groups share: consoles, option types, the debug switch, the workspace, JSON
and plain-table printing. Light on purpose (typer and the standard library): `--help` and the read-only
commands import nothing heavier."""

from __future__ import annotations

import json
import os
from typing import Annotated, Any

import typer

from capvector.flows.runtime.home import resolve_home

UNWRAPPED_WIDTH = 10_000
"""A console's width when it does not write to a terminal: wide enough that no table cell, path or id
is wrapped or cut (rich would wrap at 80 columns in a pipe, and a wrapped path cannot be pasted)."""


class _LazyConsole:
    """A rich Console made on first use: `sql` and `--help` never need rich's import (~30 ms). Written
    to a pipe or file, it wraps nothing: lines are as long as their content (`UNWRAPPED_WIDTH`)."""

    def __init__(self, **options: Any):
        self._options, self._console = options, None

    def __getattr__(self, name: str) -> Any:
        if self._console is None:
            import sys

            from rich.console import Console

            stream = sys.stderr if self._options.get("stderr") else sys.stdout
            tty = getattr(stream, "isatty", lambda: False)()
            unwrapped = {} if tty else {"soft_wrap": True, "width": UNWRAPPED_WIDTH}
            self._console = Console(**{**unwrapped, **self._options})
        return getattr(self._console, name)


def Table(*columns: str) -> Any:  # noqa: N802 (stands for rich.table.Table, imported when a table is made)
    from rich.table import Table as RichTable

    return RichTable(*columns)


console = _LazyConsole()
err = _LazyConsole(stderr=True)

HomeOption = Annotated[str | None, typer.Option("--home", help="capvector home (default: $CAPVECTOR_HOME)")]
JsonOption = Annotated[bool, typer.Option("--json", help="print machine-readable JSON")]
SetOption = Annotated[list[str] | None, typer.Option("--set", help="override a config key: a.b=value")]
DryRunOption = Annotated[
    bool, typer.Option("--dry-run", help="print the plan's steps, cached or to run, and run nothing")
]


class State:
    """Whether tracebacks are wanted (`--debug` or CAPVECTOR_DEBUG), for every command group."""

    debug: bool = os.environ.get("CAPVECTOR_DEBUG", "").lower() not in ("", "0", "false")


def workspace(home: str | None):
    """A fresh Workspace per call: opening it is what catches the catalogue up with the store."""
    from capvector.tasks.runtime.workspace import Workspace

    return Workspace(resolve_home(home))


def print_json(data: Any) -> None:
    console.print_json(json.dumps(data, default=str))


def text_table(columns: list[str], rows: list[tuple]) -> str:
    """Rows as plain aligned text (numbers to the right), whole values: no pandas, no truncation."""
    cells = [["NULL" if v is None else str(v) for v in row] for row in rows]
    numeric = [
        all(isinstance(row[i], int | float) or row[i] is None for row in rows) and bool(rows)
        for i in range(len(columns))
    ]
    widths = [max([len(c), *(len(row[i]) for row in cells)]) for i, c in enumerate(columns)]

    def line(values: list[str]) -> str:
        parts = [v.rjust(w) if num else v.ljust(w) for v, w, num in zip(values, widths, numeric, strict=True)]
        return "  ".join(parts).rstrip()

    return "\n".join([line(list(columns)), *(line(row) for row in cells)])
