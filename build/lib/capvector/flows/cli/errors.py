"""An error as the CLI prints it: one line naming the problem (the failed step first), exit 2 for bad
input and 1 for anything else; `--debug` adds the traceback."""

from __future__ import annotations

import contextlib
import sys

from capvector.artifacts.errors import ArtifactError
from capvector.flows.cli.common import State, err


def one_line(exc: BaseException, leave_out: str | None = None) -> str:
    """An error as one line: its message (a pydantic error as `field: problem` per error, DuckDB's
    multi-line messages joined), then its notes (the step it came from) but `leave_out`."""
    from pydantic import ValidationError

    if isinstance(exc, ValidationError):
        parts = []
        for e in exc.errors(include_url=False):
            where = ".".join(str(p) for p in e["loc"]) or exc.title
            got = e.get("input")
            shown = f" (got {got!r})" if isinstance(got, int | float | str) and len(repr(got)) <= 40 else ""
            parts.append(f"{where}: {e['msg']}{shown}")
        text = f"{exc.title}: " + "; ".join(parts)
    else:
        text = str(exc) or type(exc).__name__
    notes = [n for n in getattr(exc, "__notes__", ()) if isinstance(n, str) and n != leave_out]
    return " ".join(line.strip() for part in [text, *notes] for line in part.splitlines() if line.strip())


def _is_duckdb_error(exc: BaseException) -> bool:
    return type(exc).__module__.split(".")[0] in ("duckdb", "_duckdb")


def is_user_error(exc: BaseException) -> bool:
    """Bad input (exit 2): a bad value, id, path, config or query; anything else exits 1."""
    from pydantic import ValidationError

    user_errors = (ValueError, ArtifactError, ValidationError, FileNotFoundError, FileExistsError)
    # (capvector_core's CheckpointError is a ValueError; not imported: it loads numpy)
    return isinstance(exc, user_errors) or _is_duckdb_error(exc)


STEP_NOTE = "in step "  # capvector.tasks.runtime.prefect_task notes a step's error as `in step '<label>'`
FIRST_FAILURE_WAIT_S = 5.0


def failed_step(exc: BaseException) -> tuple[str, BaseException] | None:
    """(step, its error) for the flow's first failed step when `exc` is how a failure reached the CLI:
    that step's error, a later step's, or Prefect's word that a step's inputs never came."""
    steps = sys.modules.get("capvector.flows.runtime.step_submission")  # loaded where a flow ran
    if steps is None or not isinstance(exc, Exception):
        return None
    if steps.upstream_failed(exc):  # a step failed: its done-callback may still be on its way
        failure = steps.first_failure(wait_s=FIRST_FAILURE_WAIT_S)
        return (failure.step, failure.error) if failure is not None else None
    step = _step_of(exc)
    if step is None:
        return None
    failure = steps.first_failure()  # one that failed before it, if any
    return (failure.step, failure.error) if failure is not None else (step, exc)


def _step_of(exc: BaseException) -> str | None:
    """The step a step's error names in its note (capvector.tasks.runtime.prefect_task adds `in step
    '<label>'`)."""
    import ast

    for note in getattr(exc, "__notes__", ()):
        if isinstance(note, str) and note.startswith(STEP_NOTE):
            with contextlib.suppress(ValueError, SyntaxError):
                label = ast.literal_eval(note.removeprefix(STEP_NOTE))
                if isinstance(label, str):
                    return label
    return None


def fail(exc: BaseException, code: int, step: str | None = None) -> None:
    """Print the error in one line (after its traceback with --debug) and exit with `code`; a failed
    step's error as `step '<label>' failed: <its message>`."""
    if State.debug:
        import traceback

        traceback.print_exception(exc)
    text = one_line(exc, leave_out=STEP_NOTE + repr(step) if step else None)
    if code == 1:  # not a user error: say what it is and where to look
        text = f"{type(exc).__name__}: {text}" + ("" if State.debug else " (--debug shows the traceback)")
    if step is not None:
        text = f"step {step!r} failed: {text}"
    from rich.markup import escape

    # ids and paths stay whole; a tensor named like rich markup (`x[/bold]`) prints as it is
    err.print(f"[bold red]error:[/] {escape(text)}", soft_wrap=True)
    sys.exit(code)
