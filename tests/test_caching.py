"""Content cache keys, the step index, and how pipeline steps meet Prefect: a cached step is shown as
`Cached` without Prefect ever reading its result store (whose records may name the pickle serializer)."""

import hashlib
import json
import os
from pathlib import Path

from conftest import run_cli

from capvector.tasks.runtime.caching import cached_step, content_key, lookup
from capvector.tasks.runtime.prefect_task import pipeline_task
from capvector.tasks.runtime.step_code import module_closure, step_code
from capvector.tasks.runtime.workspace import Workspace


def test_step_code_covers_the_import_closure_only():
    closure = module_closure("capvector.tasks.steps.data")
    used = {
        "capvector.core.simulation.demos",
        "capvector.core.simulation.envs",
        "capvector.tasks.runtime.caching",
    }
    assert used <= set(closure)
    assert "capvector.core.training.trainer" not in closure and "capvector.flows.cli.main" not in closure
    assert "capvector.core.training.trainer" in module_closure("capvector.tasks.steps.training")
    assert step_code("capvector.tasks.steps.data") != step_code("capvector.tasks.steps.training")


def test_content_key_depends_on_inputs_config_kind_and_module():
    base = content_key("train", {"data": "a" * 64}, {"steps": 1}, "capvector.tasks.steps.training")
    assert base == content_key("train", {"data": "a" * 64}, {"steps": 1}, "capvector.tasks.steps.training")
    assert base != content_key("train", {"data": "b" * 64}, {"steps": 1}, "capvector.tasks.steps.training")
    assert base != content_key("train", {"data": "a" * 64}, {"steps": 2}, "capvector.tasks.steps.training")
    assert base != content_key("merge", {"data": "a" * 64}, {"steps": 1}, "capvector.tasks.steps.training")
    assert base != content_key("train", {"data": "a" * 64}, {"steps": 1}, "capvector.tasks.steps.data")


def _producer(workspace, calls, tmp_path):
    def produce(key):
        calls.append(key)
        src = tmp_path / f"payload-{len(calls)}.json"
        src.write_text(json.dumps({"n": 1}))
        return workspace.api.register_file(src, kind="report", name="x", config={"cache_key": key}).id

    return produce


def test_cached_step_runs_once_and_recomputes_a_vanished_artifact(tmp_path):
    workspace = Workspace(str(tmp_path / "home"))
    calls: list[str] = []
    produce = _producer(workspace, calls, tmp_path)
    first = cached_step(workspace, "report", {}, {"a": 1}, produce)
    assert cached_step(workspace, "report", {}, {"a": 1}, produce) == first
    assert len(calls) == 1

    with open(workspace.api.path(first), "r+b") as handle:  # same size, other bytes: only a hash can tell
        handle.write(b"X")
    assert lookup(workspace, calls[0]) is None
    assert cached_step(workspace, "report", {}, {"a": 1}, produce) == first  # same bytes, same id
    assert len(calls) == 2
    workspace.api.path(first, verify=True)  # the re-registration repaired the stored copy
    assert cached_step(workspace, "report", {}, {"a": 1}, produce) == first
    assert len(calls) == 2


def test_index_loss_falls_back_to_the_catalogue(tmp_path):
    workspace = Workspace(str(tmp_path / "home"))
    calls: list[str] = []
    produce = _producer(workspace, calls, tmp_path)
    first = cached_step(workspace, "report", {}, {"b": 2}, produce)
    for entry in workspace.cache_dir.glob("*.json"):
        entry.unlink()  # as if the process died between registration and the index write
    assert cached_step(workspace, "report", {}, {"b": 2}, produce) == first
    assert len(calls) == 1


# ------------------------------------------------------------------ Prefect's result store is never read
class _Planted:
    """Unpickling this appends a line to `marker` and yields `artifact_id`, as an attacker's file would
    (so a run that unpickles it still completes, and only the marker tells)."""

    def __init__(self, marker, artifact_id):
        self.marker, self.artifact_id = str(marker), artifact_id

    def __reduce__(self):
        return eval, (f"(open({self.marker!r}, 'a').write('x\\n'), {self.artifact_id!r})[1]",)


def _pickle_record(marker, artifact_id, key) -> bytes:
    from prefect._internal.result_records import ResultRecord, ResultRecordMetadata
    from prefect.serializers import PickleSerializer

    metadata = ResultRecordMetadata(storage_key=key, serializer=PickleSerializer())
    return ResultRecord(metadata=metadata, result=_Planted(marker, artifact_id)).serialize()


def test_a_planted_pickle_result_is_never_unpickled_by_a_cached_run(smoke_home, tmp_path):
    """A result record declaring the pickle serializer, under the key a cached step looks up (Prefect
    reads the serializer named inside the record), must never be loaded: the step answers from the
    content cache, and Prefect's result store is not read at all."""
    from prefect._internal.result_records import ResultRecord

    from capvector.artifacts.api import ArtifactsAPI

    home, ids = smoke_home
    storage = Path(os.environ["PREFECT_HOME"]) / "storage"  # the session's (tests/conftest.py)
    storage.mkdir(parents=True, exist_ok=True)
    marker = tmp_path / "unpickled"
    steps = ArtifactsAPI(str(home)).query(
        "SELECT id, json_extract_string(config, '$.cache_key') AS cache_key FROM artifacts "
        "WHERE json_extract_string(config, '$.cache_key') IS NOT NULL"
    )
    assert len(steps) >= 15
    for row in steps.itertuples():
        # the key a cached step looked up: sha256 of "<content key>:<id of its verified artifact>"
        key = hashlib.sha256(f"{row.cache_key}:{row.id}".encode()).hexdigest()
        (storage / key).write_bytes(_pickle_record(marker, row.id, key))

    probe = tmp_path / "probe"  # the planted records are live: loading one runs its payload
    ResultRecord.deserialize(_pickle_record(probe, "x", "k"))
    assert probe.exists()

    again = json.loads(run_cli("run", "--preset", "smoke", "--json", home=home).stdout)
    assert not marker.exists(), f"planted pickles were loaded {len(marker.read_text().split())} times"
    assert again == ids


@pipeline_task("toy_step")
def toy_step(home: str, step: str, inputs: dict, config: dict) -> str:
    workspace = Workspace(home)

    def produce(key: str) -> str:
        return workspace.api.register_json(config, kind="report", name=step, config={"cache_key": key}).id

    return cached_step(workspace, "toy_step", inputs, config, produce)


def test_cached_steps_show_as_cached_without_touching_prefects_result_store(tmp_path, monkeypatch):
    from prefect import flow
    from prefect.results import ResultStore

    reads: list[str] = []
    for name in ("_exists", "_aexists", "_read", "_aread"):
        original = getattr(ResultStore, name)

        def spy(self, key, *args, _original=original, _name=name, **kwargs):
            reads.append(f"{_name}({key})")
            return _original(self, key, *args, **kwargs)

        monkeypatch.setattr(ResultStore, name, spy)

    @flow
    def toy_flow(home: str) -> tuple:
        first = toy_step(home, "toy", {}, {"n": 1}, return_state=True)
        second = toy_step(home, "toy again", {}, {"n": 1}, return_state=True)
        return first, second

    first, second = toy_flow(str(tmp_path / "home"))
    assert (first.name, second.name) == ("Completed", "Cached")
    assert first.result() == second.result()
    assert Workspace(str(tmp_path / "home")).artifact_is_intact(second.result())
    assert reads == []
