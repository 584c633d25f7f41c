"""`capvector evaluate`'s protocol options are generated from the table `EvalConfig` reads its defaults
and descriptions from: declared once, so the command and the model cannot drift apart."""

from __future__ import annotations

import typer
from typer.testing import CliRunner

from capvector.core.evaluation.fields import EVAL_FIELDS
from capvector.core.evaluation.rollouts import EvalConfig
from capvector.flows.cli.eval_options import eval_options
from tests.conftest import run_cli


def test_every_user_set_eval_config_field_is_in_the_table_with_its_default_and_description():
    fields = EvalConfig.model_fields
    # the protocol fields `evaluate` does not expose: the task list is its own option, and test
    # goals start at the protocol's seed base (validation goals are a study's business)
    assert set(fields) - set(EVAL_FIELDS) == {"tasks", "seed_base"}
    for name, spec in EVAL_FIELDS.items():
        assert fields[name].default == spec.default, name
        assert fields[name].description == spec.help, name


def test_generated_options_reach_the_command_as_eval_config_fields():
    seen = {}
    app = typer.Typer()

    @app.command()
    @eval_options
    def probe(tasks: str, eval_settings: dict | None = None) -> None:
        seen.update(EvalConfig(tasks=tasks.split(","), **eval_settings).model_dump())

    flags = ["--episodes", "3", "--horizon", "40", "--obs-mode", "pixels", "--camera", "corner3"]
    result = CliRunner().invoke(app, ["reach-v3", *flags])
    assert result.exit_code == 0, result.output
    assert seen["episodes_per_task"] == 3 and seen["horizon"] == 40
    assert seen["obs_mode"] == "pixels" and seen["camera"] == "corner3"
    assert seen["image_size"] == EVAL_FIELDS["image_size"].default  # not given: the table's default


def test_evaluate_help_lists_every_protocol_option_and_a_bad_value_names_its_field(tmp_path):
    help_text = run_cli("evaluate", "--help", home=tmp_path / "home").stdout
    for spec in EVAL_FIELDS.values():
        assert spec.flag in help_text, spec.flag
    args = ("evaluate", "abcdef012345", "--tasks", "reach-v3", "--image-size", "8")
    proc = run_cli(*args, home=tmp_path / "home", check=False)
    assert proc.returncode == 2, proc.stderr
    assert "image_size" in proc.stderr and "Traceback" not in proc.stderr
