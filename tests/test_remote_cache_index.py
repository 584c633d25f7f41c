"""A remote home's content-cache index in the store: a brand-new machine (a fresh CAPVECTOR_CACHE,
so no step-cache folder and no catalogue) answers a cached step from `index/<key[:2]>/<key>.json`
with one GET, never listing the store; an index object that names another artifact, or is not an
entry at all, is refused with one warning line and the step recomputed. A driver indexes the ids
its steps return (`ArtifactsAPI.adopt`) from their sidecars, also without listing.

The S3 calls are counted where s3fs makes them (`S3FileSystem._call_s3`), so a listing by any
path (ls, find, glob, a catalogue catch-up) is seen."""

import collections
import json
import uuid

import pytest

pytest.importorskip("moto.server")
s3fs = pytest.importorskip("s3fs")
boto3 = pytest.importorskip("boto3")

from capvector.tasks.runtime.caching import cached_step, content_key  # noqa: E402
from capvector.tasks.runtime.workspace import Workspace  # noqa: E402

MODULE = "capvector.tasks.runtime.caching"  # the step code a key hashes: any module will do
LISTINGS = {"list_objects", "list_objects_v2", "list_buckets"}


@pytest.fixture
def home(s3_endpoint):
    bucket = f"capvector-{uuid.uuid4().hex[:12]}"
    boto3.client("s3").create_bucket(Bucket=bucket)
    return f"s3://{bucket}/home"


@pytest.fixture
def s3_calls(monkeypatch):
    """Every S3 operation s3fs makes from here on, counted by name."""
    calls: collections.Counter[str] = collections.Counter()
    real = s3fs.S3FileSystem._call_s3

    async def counting(self, method, *args, **kwargs):
        calls[method if isinstance(method, str) else getattr(method, "__name__", str(method))] += 1
        return await real(self, method, *args, **kwargs)

    monkeypatch.setattr(s3fs.S3FileSystem, "_call_s3", counting)
    return calls


def machine(home: str, tmp_path, monkeypatch) -> Workspace:
    """A new machine: a local cache folder of its own (no step-cache entries, no catalogue)."""
    monkeypatch.setenv("CAPVECTOR_CACHE", str(tmp_path / f"cache-{uuid.uuid4().hex[:8]}"))
    return Workspace(home)


def step(workspace: Workspace, calls: list[str], config: dict) -> str:
    def produce(key: str) -> str:
        calls.append(key)
        return workspace.api.register_json(config, "report", "r", config={"cache_key": key}).id

    return cached_step(workspace, "report", {}, config, produce, module=MODULE)


def index_object(workspace: Workspace, key: str) -> dict:
    return json.loads(workspace.api.store.index_entry(key))


def test_a_new_machine_answers_from_the_index_object_without_listing(home, tmp_path, monkeypatch, s3_calls):
    first = machine(home, tmp_path, monkeypatch)
    produced: list[str] = []
    artifact_id = step(first, produced, {"a": 1})
    (key,) = produced
    assert key == content_key("report", {}, {"a": 1}, MODULE)
    assert index_object(first, key) == {"artifact_id": artifact_id, "cache_key": key, "recorded_under": key}

    s3_calls.clear()
    second = machine(home, tmp_path, monkeypatch)
    assert not (second.cache_dir / f"{key}.json").exists()  # nothing local to answer from
    assert step(second, produced, {"a": 1}) == artifact_id
    assert produced == [key]  # not recomputed
    assert not LISTINGS & set(s3_calls), dict(s3_calls)
    assert s3_calls["get_object"] >= 1


def test_a_forged_index_object_is_refused_and_rewritten(home, tmp_path, monkeypatch, capfd):
    first = machine(home, tmp_path, monkeypatch)
    produced: list[str] = []
    artifact_id = step(first, produced, {"b": 2})
    other = step(first, produced, {"c": 3})  # a real artifact, recorded under another key
    key = produced[0]
    store = first.api.store
    forged = {"artifact_id": other, "cache_key": key, "recorded_under": key}
    store.put_index_entry(key, json.dumps(forged).encode())
    capfd.readouterr()

    second = machine(home, tmp_path, monkeypatch)
    assert step(second, produced, {"b": 2}) == artifact_id  # recomputed: the same bytes, the same id
    assert produced[2:] == [key]
    err = capfd.readouterr().err
    assert err.count("cache entry refused") == 1 and other[:12] in err, err
    assert index_object(second, key)["artifact_id"] == artifact_id  # the recomputation rewrote it

    third = machine(home, tmp_path, monkeypatch)  # and answers the next new machine again
    assert step(third, produced, {"b": 2}) == artifact_id and len(produced) == 3


@pytest.mark.parametrize(
    "content",
    [b'{"artifact_id": "abc', b'{"artifact_id": "abcdef"}', b"x" * 5000],
    ids=["cut-short", "prefix-id", "oversized"],
)
def test_an_unreadable_index_object_is_a_miss_with_one_warning(home, tmp_path, monkeypatch, capfd, content):
    first = machine(home, tmp_path, monkeypatch)
    produced: list[str] = []
    artifact_id = step(first, produced, {"d": 4})
    first.api.store.put_index_entry(produced[0], content)
    capfd.readouterr()

    second = machine(home, tmp_path, monkeypatch)
    assert step(second, produced, {"d": 4}) == artifact_id
    assert len(produced) == 2  # a miss: recomputed, never trusted
    assert capfd.readouterr().err.count("warning: ") == 1
    assert index_object(second, produced[0])["artifact_id"] == artifact_id


def test_the_driver_adopts_returned_ids_with_their_ancestors_without_listing(
    home, tmp_path, monkeypatch, s3_calls
):
    worker = machine(home, tmp_path, monkeypatch)
    data = worker.api.register_json({"x": 1}, "dataset", "d").id
    child = worker.api.register_json({"y": 2}, "report", "r", parents=[(data, "data")]).id

    driver = machine(home, tmp_path, monkeypatch)
    s3_calls.clear()
    assert driver.api.adopt([child]) == 2
    assert driver.api.adopt([child]) == 0  # known: nothing read again
    assert not LISTINGS & set(s3_calls), dict(s3_calls)
    assert driver.api.catalogue.known([child, data]) == {child, data}
    rows = driver.api.catalogue.query_rows("SELECT parent, role FROM edges WHERE child = ?", [child])[1]
    assert rows == [(data, "data")]
