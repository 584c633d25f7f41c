"""Nothing wrong is recorded under a trusted id: through the CLI, a checkpoint whose shards leave its
folder, or whose safetensors header is malformed, is refused in one line (exit 2) and nothing is stored.

The real console entry point (`run_cli`, a subprocess) shows the exit code and the line a user sees; the
full table of malformed headers goes through typer's CliRunner on the same app (in process, fast): it
checks the error that `main` prints as that one line.
"""

import json

import pytest
from conftest import run_cli
from test_safetensors_io import MALFORMED, _tensors, write_raw
from typer.testing import CliRunner

from capvector.artifacts.api import ArtifactsAPI
from capvector.core.vectors.safetensors_io import INDEX_NAME, Checkpoint, CheckpointError, write_checkpoint
from capvector.flows.cli.main import app


def _artifact_count(home) -> int:
    return int(ArtifactsAPI(str(home)).query("SELECT count(*) AS n FROM artifacts")["n"][0])


def _escaping_checkpoint(tmp_path, how: str):
    """A sharded checkpoint `ck/` one of whose shards lies outside it; returns (folder, shard name)."""
    ck = tmp_path / "ck"
    write_checkpoint(ck, _tensors(), max_shard_bytes=10_000)
    shard = Checkpoint(ck).files[-1]
    outside = tmp_path / "outside.safetensors"
    outside.write_bytes(shard.read_bytes())  # a valid shard: only where it lies is wrong
    shard.unlink()
    if how == "symlink":
        shard.symlink_to(outside)
        return ck, shard.name
    name = "../outside.safetensors" if how == "dotdot" else str(outside)
    index = json.loads((ck / INDEX_NAME).read_text())
    index["weight_map"] = {k: name if v == shard.name else v for k, v in index["weight_map"].items()}
    (ck / INDEX_NAME).write_text(json.dumps(index))
    return ck, name


@pytest.mark.parametrize("how", ["dotdot", "absolute", "symlink"])
def test_import_of_a_shard_outside_the_folder_exits_2_and_registers_nothing(tmp_path, how):
    ck, name = _escaping_checkpoint(tmp_path, how)
    home = tmp_path / "home"
    proc = run_cli("import", str(ck), home=home, check=False)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and repr(name) in lines[0], proc.stderr
    assert _artifact_count(home) == 0


@pytest.mark.parametrize("case", ["negative_offset", "length_not_dtype_times_shape"])
def test_vector_stats_on_a_malformed_file_exits_2_in_one_line(tmp_path, case):
    header, data, tensor = MALFORMED[case]
    path, home = tmp_path / f"{case}.safetensors", tmp_path / "home"
    write_raw(path, header, data)
    proc = run_cli("vector", "stats", str(path), home=home, check=False)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and f"tensor {tensor!r}" in lines[0], proc.stderr
    assert _artifact_count(home) == 0


@pytest.mark.parametrize("case", list(MALFORMED))
def test_vector_stats_refuses_each_malformed_header(tmp_path, case):
    header, data, tensor = MALFORMED[case]
    path, home = tmp_path / f"{case}.safetensors", tmp_path / "home"
    write_raw(path, header, data)
    result = CliRunner().invoke(app, ["--home", str(home), "vector", "stats", str(path)])
    exc = result.exception
    assert isinstance(exc, CheckpointError), (result.output, exc)
    assert "\n" not in str(exc) and f"tensor {tensor!r}" in str(exc) and str(path) in str(exc), exc
    assert _artifact_count(home) == 0
