"""Every field a preset user edits is documented (issue 22, item 4), and `capvector config show` prints it.

`capvector.flows.cli.config_commands.describe` yields each leaf field of a resolved preset with the
description its model carries (`Field(description=...)` or its class's `Args:` line); a field added without
one fails here, naming the preset and the dotted path a user would `--set`.
"""

import json

import pytest
import yaml
from typer.testing import CliRunner

from capvector.flows.calibration.config import load_calibration
from capvector.flows.cli.config_commands import describe
from capvector.flows.cli.main import app
from capvector.flows.recipe.config import PRESET_DIR, load_config
from capvector.flows.study.config import load_study

PRESETS = sorted(p.stem for p in PRESET_DIR.glob("*.yaml"))


def _load(preset: str, overrides: list[str] | None = None):
    data = yaml.safe_load((PRESET_DIR / f"{preset}.yaml").read_text()) or {}
    if "rule" in data:  # a calibration (capvector.flows.calibration.config)
        return load_calibration(preset, overrides)
    return load_study(preset, overrides) if "study" in data else load_config(preset, overrides)


def _undocumented(config) -> list[str]:
    return [path for path, _, text in describe(config) if not text.strip()]


def test_presets_are_found():
    assert {"smoke", "quick", "hard", "paper", "study-smoke", "study-control", "study-pixels"} <= set(PRESETS)
    assert {"calibrate-control", "calibrate-smoke"} <= set(PRESETS)


@pytest.mark.parametrize("preset", PRESETS)
def test_every_preset_field_has_a_description(preset):
    config = _load(preset)
    rows = list(describe(config))
    assert len(rows) > 100  # the whole config, nested models expanded
    assert len({path for path, _, _ in rows}) == len(rows)
    assert _undocumented(config) == [], f"preset {preset}: fields without a description"


@pytest.mark.parametrize(
    "overrides",
    [
        ["policy.type=flow"],  # the other built-in policy type: its own fields
        ["pretrain.aux={name: dynamics, weight: 0.5}"],  # an optional nested model, set
    ],
)
def test_fields_a_preset_can_switch_on_have_a_description(overrides):
    config = load_config("smoke", overrides)
    paths = [path for path, _, _ in describe(config)]
    assert any(p.startswith(("policy.integration_steps", "pretrain.aux.")) for p in paths)
    assert _undocumented(config) == []


def _show(*args: str) -> str:
    result = CliRunner().invoke(app, ["config", "show", "--preset", "study-smoke", *args])
    assert result.exit_code == 0, result.output
    return result.output


def test_config_show_prints_an_override_with_its_description():
    rows = {path: (value, text) for path, value, text in describe(load_study("study-smoke"))}
    out = _show("--set", "study.draws=[0,1,2]")
    lines = out.splitlines()
    assert lines[0] == f"# study preset study-smoke ({len(rows)} fields)"
    [line] = [line for line in lines if line.startswith("study.draws ")]
    assert "= [0, 1, 2]" in line
    description = rows["study.draws"][1]
    assert description and line.endswith(f"    # {description}")
    # every field is on its own line, described
    assert len(lines) == 1 + len(rows)
    assert all("    # " in line for line in lines[1:])


def test_config_show_json_gives_the_same_rows():
    overrides = ("--set", "study.draws=[0,1,2]")
    table = _show(*overrides).splitlines()[1:]
    data = json.loads(_show(*overrides, "--json"))
    assert [row["field"] for row in data] == [line.split(" = ")[0].rstrip() for line in table]
    by_field = {row["field"]: row for row in data}
    assert by_field["study.draws"]["value"] == [0, 1, 2]
    assert by_field["study.draws"]["description"]
    for row, line in zip(data, table, strict=True):
        shown = json.dumps(row["value"], ensure_ascii=False)
        assert line.split(" = ", 1)[1].startswith(shown)
        assert line.endswith(f"    # {row['description']}")
    expected = [
        {"field": p, "value": v, "description": d}
        for p, v, d in describe(load_study("study-smoke", ["study.draws=[0,1,2]"]))
    ]
    assert data == json.loads(json.dumps(expected))
