"""A score lives in one place: the evaluation's document, read through the catalogue
(capvector.artifacts.scores).

Evaluations recorded before this carried `mean_success`/`success_rates` in their sidecar config. Here
such sidecars hold deliberately wrong copies, so any reader still using them would show 0 %.
"""

import json

import pytest
from conftest import old_report
from typer.testing import CliRunner

from capvector.artifacts.api import ArtifactsAPI
from capvector.artifacts.scores import read_scores
from capvector.flows.cli.main import app
from capvector.flows.evaluation.flow import _latest_scores
from capvector.flows.recipe.report import write_report
from capvector.flows.views.comparison import compare_checkpoints
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.steps.reporting import ReportRun, load_report

REACH, DRAWER = "reach-v3", "drawer-close-v3"
STALE = {"success_rates": {REACH: 0.0, DRAWER: 0.0}, "mean_success": 0.0, "wall_time_s": 1.0}


def _episodes(successes: dict[str, list[bool]]) -> list[dict]:
    return [
        {"task": task, "seed": 100000 + i, "success": ok, "steps": 5, "return": float(ok)}
        for task, oks in successes.items()
        for i, ok in enumerate(oks)
    ]


def _evaluate(
    api: ArtifactsAPI, checkpoint: str, successes: dict[str, list[bool]], fp: str = "f" * 64
) -> str:
    doc = {"checkpoint_id": checkpoint, "fingerprint": fp, "episodes": _episodes(successes)}
    return api.register_evaluation(doc, name="evaluate", config=STALE).id


def _checkpoint(api: ArtifactsAPI, name: str) -> str:
    config = {"summary": {"steps": 20, "steps_per_s": 10.0, "trainable_parameters": 123}}
    return api.register_json({"w": name}, "checkpoint", name, config=config).id


@pytest.fixture
def scored(tmp_path):
    """Checkpoints A 75 % (reach 1/2, drawer 2/2) and B 25 % (reach 0/2, drawer 1/2), one evaluation each."""
    ws = Workspace(str(tmp_path / "home"))
    a, b = _checkpoint(ws.api, "A"), _checkpoint(ws.api, "B")
    eval_a = _evaluate(ws.api, a, {REACH: [True, False], DRAWER: [True, True]})
    eval_b = _evaluate(ws.api, b, {REACH: [False, False], DRAWER: [False, True]})
    return ws, {"A": a, "B": b, "eval_A": eval_a, "eval_B": eval_b}


def cli(home, *args: str, code: int = 0):
    result = CliRunner().invoke(app, ["--home", str(home), *args])
    assert result.exit_code == code, (result.output, result.exception)
    return result


def test_read_scores_derives_from_the_document_not_the_sidecar(scored):
    ws, ids = scored
    assert ws.api.get(ids["eval_A"]).config["mean_success"] == 0.0  # the stale copy is there
    (a,) = read_scores(ws.api, evaluations=[ids["eval_A"]])
    assert (a.checkpoint_id, a.fingerprint) == (ids["A"], "f" * 64)
    assert a.success_rates == {DRAWER: 1.0, REACH: 0.5} and a.mean_success == 0.75
    assert a.episodes == {DRAWER: 2, REACH: 2}
    by_checkpoint = read_scores(ws.api, checkpoints=[ids["B"], ids["A"]])
    assert {s.evaluation_id: s.mean_success for s in by_checkpoint} == {
        ids["eval_A"]: 0.75,
        ids["eval_B"]: 0.25,
    }
    with pytest.raises(ValueError, match="is a checkpoint, not an evaluation"):
        read_scores(ws.api, evaluations=[ids["A"]])


def test_every_reader_reports_the_documents_score_and_they_agree(scored, tmp_path):
    ws, ids = scored
    home = ws.home
    expected = {ids["A"]: {DRAWER: 1.0, REACH: 0.5}, ids["B"]: {DRAWER: 0.5, REACH: 0.0}}

    report_id = old_report(ws, {"A/seed0": ids["eval_A"], "B/seed0": ids["eval_B"]})  # a record, still read
    report = load_report(ws, report_id)
    assert {r.checkpoint_id: r.success_rates for row in report.arms.values() for r in row.runs} == expected
    assert report.arms["A"].overall.mean == 0.75 and report.arms["B"].per_task[DRAWER].mean == 0.5
    assert "| A | 75.0 ± 0.0 | 100.0 ± 0.0 | 50.0 ± 0.0 |" in report.markdown

    text = write_report(ws, report_id, tmp_path / "out" / "report.md").read_text()
    assert f"| A/seed0 | `{ids['A'][:12]}` | `{ids['eval_A'][:12]}` | 75.0% |" in text
    assert f"| B/seed0 | `{ids['B'][:12]}` | `{ids['eval_B'][:12]}` | 25.0% |" in text

    compared = json.loads(cli(home, "compare", ids["A"][:12], ids["B"], "--json").stdout)
    assert {r["checkpoint_id"]: r["success_rates"] for r in compared["rows"]} == expected
    assert [r["mean"] for r in compared["rows"]] == [0.75, 0.25] and compared["fingerprint"] == "f" * 64
    assert "75.0%" in cli(home, "compare", ids["A"], ids["B"]).stdout

    for checkpoint in (ids["A"], ids["B"]):
        rows = json.loads(cli(home, "scores", checkpoint, "--json").stdout)
        assert {r["task"]: r["success_rate"] for r in rows} == expected[checkpoint]
        assert _latest_scores(ws, checkpoint) == {"f" * 64: expected[checkpoint]}  # reevaluate's "previous"


def test_catalogue_rebuild_derives_the_scores_again(scored):
    ws, ids = scored
    before = read_scores(ws.api, checkpoints=[ids["A"], ids["B"]])
    ws.api.catalogue.path.unlink()
    assert read_scores(ArtifactsAPI(ws.home), checkpoints=[ids["A"], ids["B"]]) == before  # caught up on open
    out = json.loads(cli(ws.home, "catalogue", "rebuild", "--json").stdout)
    assert out["artifacts"] == 4 and out["corrupt"] == []
    assert read_scores(ArtifactsAPI(ws.home), checkpoints=[ids["A"], ids["B"]]) == before
    assert [s.mean_success for s in before] == [0.75, 0.25]


def test_an_evaluation_without_a_row_yet_is_read_from_its_document(scored):
    """Registered by another process while the catalogue was locked: the sidecar is committed, the row
    waits. A reader in this process must not fail or fall back to the sidecar."""
    ws, ids = scored
    doc = {"checkpoint_id": ids["B"], "fingerprint": "e" * 64, "episodes": _episodes({REACH: [True, True]})}
    late = ws.api.store.put_json(doc, "evaluation", "late", STALE, [(ids["B"], "checkpoint")]).id
    assert ws.api.query("SELECT count(*) n FROM eval_tasks WHERE evaluation_id = ?", [late])["n"][0] == 0
    (score,) = read_scores(ws.api, evaluations=[late])
    assert (score.success_rates, score.episodes, score.fingerprint) == ({REACH: 1.0}, {REACH: 2}, "e" * 64)


def test_mixed_protocols_are_refused(scored):
    ws, ids = scored
    _evaluate(ws.api, ids["B"], {REACH: [True]}, fp="e" * 64)
    with pytest.raises(ValueError, match="share 0 evaluation protocols"):
        compare_checkpoints(ws, [ids["B"], _checkpoint(ws.api, "never evaluated")], None)
    _evaluate(ws.api, ids["A"], {REACH: [True]}, fp="e" * 64)
    with pytest.raises(ValueError, match="share 2 evaluation protocols"):
        compare_checkpoints(ws, [ids["A"], ids["B"]], None)
    result = compare_checkpoints(ws, [ids["A"], ids["B"]], "e" * 8)
    assert [r.success_rates for r in result.rows] == [{REACH: 1.0}, {REACH: 1.0}]


def test_an_old_report_is_read_through_the_model(scored):
    """Read through `Report`: the stored JSON is exactly its dump, and reads back equal."""
    ws, ids = scored
    report_id = old_report(ws, {"A/seed0": ids["eval_A"]})
    stored = ws.api.store.open_json(report_id)
    assert stored == load_report(ws, report_id).model_dump(mode="json")
    assert set(stored) == {"fingerprint", "arms", "markdown"}
    assert set(stored["arms"]["A"]["runs"][0]) == set(ReportRun.model_fields)


def test_smoke_run_records_no_score_in_a_sidecar_and_readers_agree(smoke_home):
    home, ids = smoke_home
    ws = Workspace(str(home))
    evaluations = ids["evaluations"]
    scores = {s.evaluation_id: s for s in read_scores(ws.api, evaluations=evaluations.values())}
    study = ws.api.store.open_json(ids["report"])  # one seed, the final budget alone: its endpoint
    for label, eval_id in evaluations.items():
        config = ws.api.get(eval_id).config
        assert not {"mean_success", "success_rates"} & set(config), config
        per_task = study["per_task"][label.split("/")[0]]
        assert per_task == {t: 100 * v for t, v in scores[eval_id].success_rates.items()}, label
    checkpoints = [ids["checkpoints"][label] for label in evaluations]
    fingerprint = scores[evaluations["sft/seed0"]].fingerprint
    compared = compare_checkpoints(ws, checkpoints, fingerprint)
    for row in compared.rows:
        latest = [
            s for s in read_scores(ws.api, checkpoints=[row.checkpoint_id]) if s.fingerprint == fingerprint
        ]
        assert row.success_rates == latest[-1].success_rates


# --------------------------------------------------------------------------- protocols by name (issue 24)
FP_TEST = "abcdef01" + "1" * 56
FP_VALIDATION = "abcdef02" + "2" * 56


def _evaluate_at(api: ArtifactsAPI, checkpoint: str, fp: str, seed_base: int, ok: bool) -> str:
    episodes = [
        {"task": REACH, "seed": seed_base + i, "success": ok, "steps": 5, "return": float(ok)}
        for i in range(2)
    ]
    doc = {"checkpoint_id": checkpoint, "fingerprint": fp, "episodes": episodes}
    return api.register_evaluation(doc, "e").id


@pytest.fixture
def two_protocols(tmp_path):
    """Checkpoint C scored 100 % under the test protocol and 0 % under the validation one."""
    api = ArtifactsAPI(str(tmp_path / "home"))
    c = _checkpoint(api, "C")
    _evaluate_at(api, c, FP_TEST, 100_000, True)
    _evaluate_at(api, c, FP_VALIDATION, 50_000, False)
    return api.home, c


def test_protocol_names_are_the_seed_bases_of_capvector_core():
    from capvector.core.simulation.demos import EVAL_SEED_BASE, VALIDATION_SEED_BASE
    from capvector.flows.evaluation.protocols import NAMES

    assert NAMES == {"test": EVAL_SEED_BASE, "validation": VALIDATION_SEED_BASE}


def test_scores_under_several_protocols_name_them_and_the_flag(two_protocols):
    home, c = two_protocols
    error = cli(home, "scores", c, code=1).exception
    assert isinstance(error, ValueError), error  # main() turns it into one line and exit 2
    text = str(error)
    assert "--fingerprint" in text and "fingerprint=" not in text
    assert f"{FP_TEST[:12]} test (goal seeds from 100000, 1 evaluations)" in text
    assert f"{FP_VALIDATION[:12]} validation (goal seeds from 50000, 1 evaluations)" in text


@pytest.mark.parametrize(
    ("choice", "fingerprint"),
    [("test", FP_TEST), ("validation", FP_VALIDATION), ("TEST", FP_TEST), (FP_TEST[:12], FP_TEST),
     (FP_VALIDATION[:8], FP_VALIDATION), (FP_VALIDATION, FP_VALIDATION), (FP_TEST[:12].upper(), FP_TEST)],
)  # fmt: skip
def test_fingerprint_by_name_or_unique_prefix(two_protocols, choice, fingerprint):
    home, c = two_protocols
    rows = json.loads(cli(home, "scores", c, "--fingerprint", choice, "--json").stdout)
    expected = [(fingerprint, float(fingerprint == FP_TEST))]
    assert [(r["fingerprint"], r["success_rate"]) for r in rows] == expected
    assert rows[0]["protocol"] == ("test" if fingerprint == FP_TEST else "validation")
    table = cli(home, "scores", c[:12], "--fingerprint", choice).stdout
    name = "test" if fingerprint == FP_TEST else "validation"
    assert table.splitlines()[-1].startswith(f"protocol {fingerprint[:12]} {name} (goal seeds from ")


@pytest.mark.parametrize(
    ("choice", "problem"),
    [("abcdef0", "matches 2 evaluation protocols"), ("999999", "matches no evaluation protocols"),
     ("abc", "is not a protocol name or fingerprint prefix"), ("tests", "is not a protocol name")],
)  # fmt: skip
def test_ambiguous_unknown_or_short_fingerprints_are_errors_listing_choices(two_protocols, choice, problem):
    home, c = two_protocols
    error = cli(home, "scores", c, "--fingerprint", choice, code=1).exception
    assert isinstance(error, ValueError) and problem in str(error), error
    assert f"{FP_TEST[:12]} test" in str(error) and f"{FP_VALIDATION[:12]} validation" in str(error)


def test_one_protocol_still_checks_the_choice(two_protocols, tmp_path):
    home, c = two_protocols
    api = ArtifactsAPI(home)
    d = _checkpoint(api, "D")
    _evaluate_at(api, d, FP_TEST, 100_000, True)
    rows = json.loads(cli(home, "scores", d, "--fingerprint", "test", "--json").stdout)
    assert rows[0]["protocol"] == "test"
    error = cli(home, "scores", d, "--fingerprint", "validation", code=1).exception
    assert "none of" in str(error) and "validation goal seeds (50000)" in str(error), error


def test_the_console_entry_point_exits_2_with_one_line(two_protocols):
    from conftest import run_cli

    home, c = two_protocols
    proc = run_cli("scores", c, "--fingerprint", "abcdef0", home=home, check=False)
    assert proc.returncode == 2, proc.stderr
    (line,) = [x for x in proc.stderr.splitlines() if x.strip()]
    assert line.startswith("error: --fingerprint 'abcdef0' matches 2") and "--fingerprint test" in line
