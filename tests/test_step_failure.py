"""A failed flow names the step that failed first and its error, in one line, whatever the flow was
waiting for when it failed; `--debug` keeps the traceback.

A flow that waits for the end of a chain whose first step failed gets only Prefect's word that the
step's inputs never came (`UpstreamTaskError` from a pool, `UnfinishedRun` from a thread runner:
"Upstream task run '<uuid>' did not reach a 'COMPLETED' state"), which names neither the step nor the
error: the CLI printed that. Here a toy chain of three steps runs through the real console entry point
(capvector.flows.cli.main.main, with the real step runners), as `capvector study` would when a study's step
fails.
"""

import os
import subprocess
import sys
import textwrap

import pytest
from conftest import REPO, run_in_session

TOY_CLI = textwrap.dedent(
    """
    from prefect import flow

    from capvector.flows.cli import main as cli
    from capvector.flows.cli.experiment_commands import FLOW_COMMANDS, preflight
    from capvector.flows.runtime.home import resolve_home
    from capvector.flows.runtime.task_runners import RunnerConfig, build_runner
    from capvector.flows.runtime.step_submission import StepRunner, resolve
    from capvector.tasks.runtime.prefect_task import pipeline_task


    @pipeline_task("toy step", content_cached=False)
    def toy_task(home, step, inputs, config):
        if config.get("error"):
            raise ValueError(config["error"])
        return "id-" + step.replace(" ", "-")


    @flow(name="toy-chain", persist_result=False)
    def chain(home: str) -> str:
        steps = StepRunner(home, 3, "toy chain")
        first = steps.submit(toy_task, "first step", {}, {"error": "the first step's own error"})
        second = steps.submit(toy_task, "second step", {"input": first}, {})
        third = steps.submit(toy_task, "third step", {"input": second}, {})
        return resolve(third)  # the end of the chain first


    @cli.app.command("toy-chain")
    def toy_chain(runner: str = "process") -> None:
        home = resolve_home(None)
        preflight("toy-chain", home)
        chain.with_options(task_runner=build_runner(RunnerConfig(kind=runner, workers=1)))(home)


    if __name__ == "__main__":
        FLOW_COMMANDS.add("toy-chain")
        cli.main()
    """
)

ERROR_LINE = "error: step 'first step' failed: the first step's own error"


def _toy_cli(tmp_path, *args: str) -> subprocess.CompletedProcess:
    script = tmp_path / "toy_cli.py"
    script.write_text(TOY_CLI)
    env = {
        **os.environ,
        "CAPVECTOR_HOME": str(tmp_path / "home"),
        "CAPVECTOR_QUIET": "1",
        "PYTHONPATH": str(REPO),
    }
    env.pop("CAPVECTOR_DEBUG", None)
    return run_in_session([sys.executable, str(script), *args], env, timeout=300)


@pytest.mark.parametrize("runner", ["process", "thread"])
def test_a_failed_chain_names_its_first_failed_step_and_error_in_one_line(tmp_path, runner):
    proc = _toy_cli(tmp_path, "toy-chain", "--runner", runner)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2, proc.stderr[-4000:]  # the step's error is a ValueError: bad input
    assert lines == [ERROR_LINE], proc.stderr[-4000:]


def test_debug_keeps_the_traceback(tmp_path):
    proc = _toy_cli(tmp_path, "--debug", "toy-chain", "--runner", "thread")
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2, proc.stderr[-4000:]
    assert "Traceback" in proc.stderr, proc.stderr[-4000:]
    assert lines[-1] == ERROR_LINE, lines[-5:]
