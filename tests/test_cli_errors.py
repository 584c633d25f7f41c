"""What a user sees when a command fails: one line naming the problem (exit 2 for bad input), not a
traceback, wherever the error was raised (a preset, an override, DuckDB, inside a flow or one of its
step workers); `--debug` shows the traceback. And no command ends with DuckDB's (nanobind's) leak
report in its output.

Through the real console entry point (`run_cli`, a subprocess), as a user runs it.
"""

import os
import re
from pathlib import Path

import pytest
from conftest import run_cli

from capvector.artifacts.api import ArtifactsAPI


def _lines(text: str) -> list[str]:
    """Non-empty lines of stderr (run_cli sets CAPVECTOR_QUIET: no progress lines)."""
    return [line for line in text.splitlines() if line.strip()]


def _one_error_line(proc, *needles: str) -> str:
    lines = _lines(proc.stderr)
    assert len(lines) == 1, proc.stderr[-6000:]
    assert lines[0].startswith("error:"), lines
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def _datasets(home) -> int:
    if not home.exists():
        return 0
    return int(ArtifactsAPI(str(home)).query("SELECT count(*) AS n FROM artifacts")["n"][0])


BAD_TAG = """\
name: bad
splits: {pretrain: [reach-v3], extraction: [drawer-close-v3], downstream: [button-press-topdown-v3]}
alpha: !!python/object/apply:os.system ["echo unsafe"]
"""


def test_a_bad_yaml_tag_in_a_preset_is_one_line_naming_the_file_and_line(tmp_path):
    preset = tmp_path / "bad.yaml"
    preset.write_text(BAD_TAG)
    proc = run_cli("run", "--preset", str(preset), home=tmp_path / "home", check=False)
    assert proc.returncode == 2, proc.stderr
    _one_error_line(proc, str(preset), "line 3", "python/object/apply:os.system")


def test_a_preset_that_is_not_a_mapping_is_one_line(tmp_path):
    preset = tmp_path / "list.yaml"
    preset.write_text("- alpha\n- 1.1\n")
    proc = run_cli("run", "--preset", str(preset), home=tmp_path / "home", check=False)
    assert proc.returncode == 2, proc.stderr
    _one_error_line(proc, str(preset), "mapping")


@pytest.mark.parametrize("value", ["!!python/name:os.system", "[sft, aux"])
def test_a_bad_yaml_value_in_an_override_is_one_line_naming_it(tmp_path, value):
    proc = run_cli("run", "--preset", "smoke", "--set", f"arms={value}", home=tmp_path / "home", check=False)
    assert proc.returncode == 2, proc.stderr
    _one_error_line(proc, f"arms={value}", "not valid YAML")


def test_nan_alpha_is_one_line_naming_the_field_before_any_step(tmp_path):
    home = tmp_path / "home"
    proc = run_cli("run", "--preset", "smoke", "--set", "alpha=.nan", home=home, check=False)
    assert proc.returncode == 2, proc.stderr
    _one_error_line(proc, "alpha", "finite number")
    assert _datasets(home) == 0


def test_nan_alpha_on_the_vector_command_line_is_refused(tmp_path):
    base = tmp_path / "missing.safetensors"  # never read: the coefficient is checked first
    proc = run_cli("vector", "merge", str(base), "--vector", str(base), "--alpha", "nan",
                   "-o", str(tmp_path / "m.safetensors"), home=tmp_path / "home", check=False)  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    _one_error_line(proc, "--alpha", "finite")


def test_a_duckdb_error_in_sql_is_one_line_and_debug_shows_the_traceback(tmp_path):
    home = tmp_path / "home"
    proc = run_cli("sql", "SELECT * FROM no_such_table", home=home, check=False)
    assert proc.returncode == 2, proc.stderr
    _one_error_line(proc, "no_such_table")
    debug = run_cli("--debug", "sql", "SELECT * FROM no_such_table", home=home, check=False)
    assert debug.returncode == 2 and "Traceback" in debug.stderr, debug.stderr
    assert _lines(debug.stderr)[-1].startswith("error:") and "no_such_table" in _lines(debug.stderr)[-1]


def test_an_error_inside_a_flow_is_one_line_without_leak_report_and_debug_shows_it(tmp_path):
    """`capvector evaluate` of an unknown id fails inside the flow: Prefect used to log the traceback
    (28 lines), and the exit printed ~40 lines of nanobind leak warnings for DuckDB's objects."""
    home = tmp_path / "home"
    args = ("evaluate", "abcdef012345", "--tasks", "reach-v3", "--episodes", "1")
    proc = run_cli(*args, home=home, check=False)
    assert proc.returncode == 2, proc.stderr
    assert "nanobind" not in proc.stderr and "leaked" not in proc.stderr, proc.stderr[-3000:]
    _one_error_line(proc, "abcdef012345")
    debug = run_cli("--debug", *args, home=home, check=False)
    assert debug.returncode == 2 and "Traceback" in debug.stderr, debug.stderr
    assert "nanobind" not in debug.stderr, debug.stderr[-3000:]


@pytest.mark.slow
def test_a_step_failing_in_a_worker_is_one_line_naming_the_step(tmp_path):
    """The auxiliary objective's training steps fail in a step worker (an objective layer that does not
    exist), after the demos and θ_pt: one line naming the problem and the step, not the worker's
    traceback, the failed states and the flow's UpstreamTaskError naming a task-run id (~940 lines
    before). Two steps train with the objective, θ_ao and the downstream auxiliary arm, both ready once
    θ_pt is; the line names whichever failed first."""
    proc = run_cli("run", "--preset", "smoke", "--set", "aux.params={layer: 99}",
                   home=tmp_path / "home", check=False, timeout=900)  # fmt: skip
    assert proc.returncode == 2, proc.stderr[-6000:]
    assert "UpstreamTaskError" not in proc.stderr and "Traceback" not in proc.stderr, proc.stderr[-6000:]
    line = _one_error_line(proc, "99")
    assert re.search(r"step '(draw 0 auxiliary SFT θ_ao|downstream aux seed \d+)' failed", line), line
    assert "nanobind" not in proc.stderr, line


# ---------------------------------------------------------------------------- issue 38's smaller faults
PLUGIN_BODIES = {"exits": "import sys\nsys.exit(0)\n", "raises": "raise RuntimeError('no GPU here')\n"}


@pytest.mark.parametrize("how", sorted(PLUGIN_BODIES))
def test_a_policy_plugin_that_exits_or_raises_at_import_is_one_line_and_a_failure(tmp_path, how):
    """A plugin calling sys.exit(0) at import made `capvector run` exit 0 with no output."""
    plugins = tmp_path / "plugins"
    info = plugins / "broken-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: broken\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[capvector.policies]\nbroken = capvector_broken\n")
    (plugins / "capvector_broken.py").write_text(PLUGIN_BODIES[how])
    home = tmp_path / "home"
    proc = run_cli("run", "--preset", "smoke", "--set", "policy.type=broken", home=home, check=False,
                   env={"PYTHONPATH": str(plugins)})  # fmt: skip
    assert proc.returncode != 0, proc.stderr
    line = _one_error_line(proc, "'broken'", "capvector_broken")
    assert ("sys.exit(0)" if how == "exits" else "no GPU here") in line, line
    assert not home.exists()


def test_duplicate_study_arms_are_refused_before_the_home_is_made(tmp_path):
    home = tmp_path / "home"
    proc = run_cli("study", "--preset", "study-smoke", "--set", "study.arms=[sft, capvector, aux, sft]",
                   home=home, check=False)  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    _one_error_line(proc, "study.arms", "sft more than once")
    assert not home.exists()


def test_switching_a_presets_flow_policy_back_to_l1_chunk_warns_in_one_line(tmp_path):
    """Python's format gave the warning three lines: where it was raised, then that line's source."""
    from conftest import REPO

    preset = tmp_path / "presets" / "flow.yaml"  # an absolute path, as --preset takes it
    preset.parent.mkdir()
    text = (REPO / "flows" / "presets" / "smoke.yaml").read_text()
    preset.write_text(text.replace("policy: {", "policy: {type: flow, integration_steps: 5, "))
    proc = run_cli("config", "show", "--preset", str(preset), "--set", "policy.type=l1_chunk",
                   home=tmp_path / "home")  # fmt: skip
    assert _lines(proc.stderr) == [
        "warning: policy.type=l1_chunk: integration_steps do not apply to this type and were dropped"
    ], proc.stderr


@pytest.mark.parametrize("command", ["run", "study", "calibrate", "sweep"])
def test_a_preset_given_by_its_absolute_path_names_the_log_file_by_its_stem(tmp_path, monkeypatch, command):
    """`--preset /abs/path/p.yaml` failed every flow command: the log file's name kept the slashes."""
    from capvector.flows.cli import experiment_commands
    from capvector.tasks.runtime.progress import LOG_FILE_ENV

    monkeypatch.setenv(LOG_FILE_ENV, "")  # unset for _start_log, and restored after (delenv of an unset
    # variable records nothing, so the path _start_log sets would leak into every later test's CLI)
    monkeypatch.setenv("CAPVECTOR_QUIET", "1")
    home = tmp_path / "home"
    experiment_commands._start_log(f"{command} --preset {tmp_path}/my presets/study-small.v2.yaml", str(home))
    log = Path(os.environ[LOG_FILE_ENV])
    assert log.parent == home / "logs" and log.name.startswith(f"{command}-study-small.v2-"), log
    log.write_text("ok")
    assert experiment_commands.log_slug("run --preset smoke") == "run-smoke"  # names as before
