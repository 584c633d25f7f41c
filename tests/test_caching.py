"""Content cache keys and the step index (without Prefect: the layer under its task cache)."""

import json

from tasks.caching import cached_step, content_key, lookup
from tasks.code_version import code_version, module_closure
from tasks.workspace import Workspace


def test_code_version_covers_the_import_closure_only():
    closure = module_closure("tasks.data")
    assert {"capvector_core.demos", "capvector_core.envs", "tasks.caching"} <= set(closure)
    assert "capvector_core.trainer" not in closure and "flows.cli" not in closure
    assert "capvector_core.trainer" in module_closure("tasks.training")
    assert code_version("tasks.data") != code_version("tasks.training")


def test_content_key_depends_on_inputs_config_kind_and_module():
    base = content_key("train", {"data": "a" * 64}, {"steps": 1}, "tasks.training")
    assert base == content_key("train", {"data": "a" * 64}, {"steps": 1}, "tasks.training")
    assert base != content_key("train", {"data": "b" * 64}, {"steps": 1}, "tasks.training")
    assert base != content_key("train", {"data": "a" * 64}, {"steps": 2}, "tasks.training")
    assert base != content_key("merge", {"data": "a" * 64}, {"steps": 1}, "tasks.training")
    assert base != content_key("train", {"data": "a" * 64}, {"steps": 1}, "tasks.data")


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
