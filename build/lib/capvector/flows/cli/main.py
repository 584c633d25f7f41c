"""The `capvector` command line: run the recipe, inspect lineage and scores, operate on vectors.

Imports here stay light: `--help` and the read-only commands (sql, lineage, scores, artifacts, verify,
catalogue) load neither torch, pandas, prefect nor metaworld; every command imports what it runs.
"""

from __future__ import annotations

import os
import signal
import sys
import warnings
from typing import Annotated

import typer

from capvector.flows.cli import experiment_commands, inspect_commands
from capvector.flows.cli.catalogue_commands import catalogue_app
from capvector.flows.cli.common import State
from capvector.flows.cli.config_commands import config_app
from capvector.flows.cli.errors import fail, failed_step, is_user_error
from capvector.flows.cli.experiment_commands import FLOW_COMMANDS
from capvector.flows.cli.inspect_commands import artifacts_app
from capvector.flows.cli.process_tree import (
    QUIET_RESOURCE_TRACKER,
    end,
    leave_ctrl_c_to_the_cli,
    stop_on_signals,
)
from capvector.flows.cli.table_commands import export, runs
from capvector.flows.cli.vector_commands import vector_app
from capvector.flows.cli.verify_commands import verify
from capvector.flows.runtime.home import set_root_home

leave_ctrl_c_to_the_cli()


app = typer.Typer(no_args_is_help=True, add_completion=False, help=__doc__)
app.add_typer(artifacts_app, name="artifacts")
app.add_typer(vector_app, name="vector")
app.add_typer(catalogue_app, name="catalogue")
app.add_typer(config_app, name="config")
app.command("verify")(verify)
app.command("runs")(runs)
app.command("export")(export)
for name in ("run", "evaluate", "reevaluate", "study", "calibrate", "sweep", "schedule"):
    app.command()(getattr(experiment_commands, name))
for command in (inspect_commands.lineage, inspect_commands.scores, inspect_commands.compare,
                inspect_commands.report, inspect_commands.studies, inspect_commands.sql):  # fmt: skip
    app.command()(command)
app.command("import")(inspect_commands.import_checkpoint)
app.command("import-dataset")(inspect_commands.import_dataset)


@app.callback()
def main_options(
    ctx: typer.Context,
    home: Annotated[
        str | None, typer.Option("--home", envvar="CAPVECTOR_HOME", help="capvector home")
    ] = None,
    debug: Annotated[
        bool,
        typer.Option("--debug", envvar="CAPVECTOR_DEBUG", help="show tracebacks and run logs on errors"),
    ] = False,
) -> None:
    """capvector: capability vectors for VLA policies on Meta-World, with lineage."""
    set_root_home(home)
    State.debug = State.debug or debug
    if State.debug:
        os.environ["CAPVECTOR_DEBUG"] = "1"  # step workers inherit it
    if ctx.invoked_subcommand in FLOW_COMMANDS:
        from capvector.flows.runtime.prefect_server import start_run_server

        start_run_server()  # the address only: a run the content cache answers never starts the server


def one_line_warning(message: Warning | str, category: type[Warning], *_: object, **__: object) -> str:
    """A warning as the CLI's other warnings read: `warning: <message>`, one line (Python's own format
    adds the file and line it came from and, on a line of its own, that line's source)."""
    text = " ".join(str(message).split())
    return f"warning: {text}\n" if category is UserWarning else f"warning: {category.__name__}: {text}\n"


def main() -> None:
    """Console entry point: an error prints one line naming the problem and exits 2 (bad input) or 1
    (anything else), nothing half-written; `--debug` (or CAPVECTOR_DEBUG=1) shows the traceback. A
    failed flow names the step that failed first and that step's error, whichever error the flow
    raised. Ctrl-C: `interrupted`, exit 130 (see capvector.flows.cli.process_tree.stop_on_signals)."""
    terminated = stop_on_signals()
    warnings.formatwarning = one_line_warning
    if QUIET_RESOURCE_TRACKER not in sys.warnoptions:
        sys.warnoptions.append(QUIET_RESOURCE_TRACKER)
    try:
        try:
            code = app(prog_name="capvector", standalone_mode=False)  # click returns a typer.Exit's code here
        except BaseException as exc:
            if terminated():
                end(signal.SIGTERM)
            failed = failed_step(exc)
            if failed is not None:
                step, error = failed
                if State.debug and error is not exc:
                    import traceback

                    traceback.print_exception(exc)  # how the flow ended; then the step's own error
                fail(error, 2 if is_user_error(error) else 1, step)
            raise
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except typer.Abort:
        sys.exit(130)
    except Exception as exc:
        from typer._click.exceptions import ClickException  # typer vendors click

        if isinstance(exc, ClickException):  # a usage error: click's own message and code
            exc.show()
            sys.exit(exc.exit_code)
        fail(exc, 2 if is_user_error(exc) else 1)
    if isinstance(code, int) and code:
        sys.exit(code)


if __name__ == "__main__":
    main()
