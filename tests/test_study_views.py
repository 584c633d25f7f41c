"""`capvector studies`: listing a home's studies and comparing two side by side, on study documents (the
golden study-smoke report, a changed copy of it) and through the command on real study artifacts."""

import copy
import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from capvector.artifacts.api import ArtifactsAPI
from capvector.flows.cli.main import app
from capvector.flows.views import studies
from capvector.stats.paired_differences import ENDPOINT

GOLDEN = Path(__file__).parent / "data" / "study_smoke_report.json"


def _doc() -> dict:
    return json.loads(GOLDEN.read_text())


def test_the_views_endpoint_is_the_statistics_one():
    assert studies.ENDPOINT == ENDPOINT


def test_two_studies_side_by_side_show_each_ones_design_verdicts_and_differences():
    a, b = _doc(), _doc()
    b["design"]["seeds"] = [0, 1, 2, 3]
    moved = next(
        c for c in b["comparisons"] if (c["arm"], c["baseline"], c["budget"]) == ("meta_sft", "sft", -1)
    )
    moved.update(difference=7.25, ci_low=1.5, ci_high=13.0)
    b["comparisons"] = [c for c in b["comparisons"] if (c["arm"], c["baseline"]) != ("aux", "sft")]
    sections = studies.compare_studies(a, b)
    design = {row[0]: row[1:] for row in sections["design"]}
    assert design["draws × seeds"] == ("2 × 2", "2 × 4")
    assert design["chosen"][0].endswith("lambda_relative 0.1")
    rows = {row[0]: row[1:] for row in sections["comparisons at the primary endpoint (points)"]}
    original = next(
        c for c in a["comparisons"] if (c["arm"], c["baseline"], c["budget"]) == ("meta_sft", "sft", -1)
    )
    assert rows["meta_sft − sft"] == (studies.difference_cell(original), "+7.2 [+1.5, +13.0]")
    assert rows["aux − sft"][1] == "–"  # only in A
    assert len(rows) == len({(c["arm"], c["baseline"]) for c in a["comparisons"] if c["budget"] == ENDPOINT})
    verdicts = {row[0]: row[1:] for row in sections["preconditions"]}
    assert set(verdicts) == {"(a)", "(b)", "(c)", "(c′)", "(d)", "(e)"}
    assert verdicts["(a)"][0].startswith("fails") and verdicts["(e)"] == ("not measured", "not measured")


def test_a_document_that_is_not_a_study_is_refused_by_name(tmp_path):
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"arms": []}))
    with pytest.raises(ValueError, match="other.json' is not a study report"):
        studies.load_study_doc(None, str(other))


def test_the_command_lists_studies_and_compares_an_artifact_with_a_file(tmp_path):
    home = tmp_path / "home"
    api = ArtifactsAPI(str(home))
    a = api.register_json(_doc(), "study", "study study-smoke").id
    gate = copy.deepcopy(_doc())
    gate["design"]["stage"], gate["gate"] = "gate", "(c′) not shown"
    b = api.register_json(gate, "study", "study study-smoke gate").id
    api.register_json({"x": 1}, "report", "a pipeline report")
    runner = CliRunner()
    listed = runner.invoke(app, ["--home", str(home), "studies", "--json"])
    assert listed.exit_code == 0, listed.output
    rows = {r["id"]: r for r in json.loads(listed.stdout)}
    assert set(rows) == {a, b}
    assert (rows[b]["stage"], rows[b]["gate"], rows[a]["gate"]) == ("gate", "failed", "not used")
    assert rows[a]["headline"].startswith("meta_sft − sft ")
    exported = tmp_path / "b.json"
    exported.write_text(json.dumps(gate))
    shown = runner.invoke(app, ["--home", str(home), "studies", a[:10], str(exported)])
    assert shown.exit_code == 0, shown.output
    assert "comparisons at the primary endpoint" in shown.stdout and "b.json" in shown.stdout
    wrong = runner.invoke(app, ["--home", str(home), "studies", a[:10]])
    assert wrong.exit_code != 0 and "give two studies" in wrong.output
