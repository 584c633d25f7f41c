"""Issue 36: merged folders that load where their base loaded, real checkpoints accepted (dtypes, key
prefixes, the base checked by content), and any registered policy folder evaluated."""

import json
import shutil

import pytest
import torch
from safetensors.torch import save_file
from typer.testing import CliRunner

from capvector.core.policies.base import PolicyLoadError, build_policy, load_policy, save_policy
from capvector.core.vectors.safetensors_io import INDEX_NAME, Checkpoint, CheckpointError, write_checkpoint
from capvector.core.vectors.vector_ops import VectorOpError, extract, merge
from capvector.flows.cli.main import app
from capvector.tasks.runtime.workspace import Workspace

CONFIG = b'{\n  "type": "act",\n  "chunk_size": 8\n}\n'  # bytes as a user's tool wrote them


def _weights(seed: int, dtype=torch.float32, prefix: str = "") -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        f"{prefix}enc.weight": torch.randn(8, 6, generator=g).to(dtype),
        f"{prefix}enc.bias": torch.randn(8, generator=g).to(dtype),
        f"{prefix}head.weight": torch.randn(3, 8, generator=g).to(dtype),
        f"{prefix}steps": torch.tensor([7], dtype=torch.int64),
    }


def _folder(path, tensors, layout: str):
    """A LeRobot-style folder (config.json, train_config.json, a processor, model.safetensors) or a
    Hugging Face sharded one (config.json, generation_config.json, shards + index)."""
    path.mkdir()
    (path / "config.json").write_bytes(CONFIG)
    if layout == "lerobot":
        (path / "train_config.json").write_text('{"steps": 100}')
        save_file({"mean": torch.zeros(3)}, str(path / "policy_preprocessor_step_0.safetensors"))
        save_file(tensors, str(path / "model.safetensors"))
    else:
        (path / "generation_config.json").write_text("{}")
        write_checkpoint(path / "w", tensors, max_shard_bytes=200)
        for f in (path / "w").iterdir():
            f.rename(path / f.name)
        (path / "w").rmdir()
    return path


def _cli(home, *args):
    result = CliRunner().invoke(app, ["--home", str(home), *args])
    assert result.exit_code == 0, (result.output, result.exception)
    return result.output.split("(artifact ")[1].split(")")[0].strip()


def _files(path):
    return sorted(f.relative_to(path).as_posix() for f in path.rglob("*") if f.is_file())


# ---------------------------------------------------------------------------- 1. outputs that load
@pytest.mark.parametrize("layout", ["lerobot", "hf_sharded"])
def test_folders_round_trip_extract_merge_with_files_index_and_card(tmp_path, layout):
    home = tmp_path / "home"
    pt, ft, ao = (_folder(tmp_path / n, _weights(s), layout) for s, n in enumerate(["pt", "ft", "ao"]))
    shard = ["--out-shard-size", "200"] if layout == "hf_sharded" else []
    gamma_id = _cli(home, "vector", "extract", str(ao), str(ft), "-o", str(tmp_path / "gamma"), *shard)
    merged = tmp_path / "merged"
    merged_id = _cli(
        home, "vector", "merge", str(pt), "--vector", str(tmp_path / "gamma"), "--alpha", "0.5",
        "-o", str(merged), *shard,
    )  # fmt: skip
    assert _files(merged) == sorted([*_files(pt), "README.md"])
    assert (merged / "config.json").read_bytes() == (pt / "config.json").read_bytes()
    if layout == "hf_sharded":
        assert json.loads((merged / INDEX_NAME).read_text())["weight_map"].keys() == _weights(0).keys()
    got = dict(Checkpoint(merged).items())
    base, gamma = _weights(0), {k: _weights(2)[k] - _weights(1)[k] for k in _weights(0)}
    for k, v in base.items():
        want = v if not v.is_floating_point() else v + 0.5 * gamma[k]
        torch.testing.assert_close(got[k], want)
    card = (merged / "README.md").read_text()
    ws = Workspace(str(home))
    parents = {p.role: p.id for p in ws.api.get(merged_id).parents}
    assert "base + sum_i alpha_i * vector_i" in card and "| vector_0 | 0.5 |" in card
    assert parents["base"] in card and gamma_id in card and Checkpoint(pt).sha256() in card
    assert f"capvector vector merge {parents['base']} --vector {gamma_id} --alpha 0.5" in card
    assert "numpy" in card and "safetensors" in card
    assert (tmp_path / "gamma" / "config.json").read_bytes() == CONFIG  # extract carries the minuend's

    # by artifact id: the stored folder's files come along too
    pt_id = parents["base"]  # the stored copy of the base folder
    by_id = tmp_path / "by_id"
    _cli(home, "vector", "merge", pt_id, "--vector", gamma_id, "--alpha", "0.5", "-o", str(by_id), *shard)
    assert _files(by_id) == _files(merged)
    assert (by_id / "config.json").read_bytes() == CONFIG


# ---------------------------------------------------------------------------- 2. real checkpoints
def test_bf16_finetune_against_fp32_base_needs_dtype_and_writes_out_dtype(tmp_path):
    save_file(_weights(0), str(pt := tmp_path / "pt.safetensors"))
    save_file(_weights(1, torch.bfloat16), str(ft := tmp_path / "ft.safetensors"))
    with pytest.raises(VectorOpError, match="--dtype float32"):
        extract(ft, pt, tmp_path / "refused.safetensors")
    assert not (tmp_path / "refused.safetensors").exists()
    tau = extract(ft, pt, tmp_path / "tau.safetensors", dtype="float32", out_dtype="float32")
    got = dict(Checkpoint(tau).items())
    for k, v in _weights(0).items():
        if v.is_floating_point():
            assert got[k].dtype == torch.float32
            torch.testing.assert_close(got[k], _weights(1, torch.bfloat16)[k].float() - v)
    # merged into the fp32 base (default: base's dtype), or written as bf16
    same = merge(pt, [(tau, 1.0)], tmp_path / "m32.safetensors", dtype="float32")
    assert Checkpoint(same).specs["enc.weight"].dtype == "F32"
    low = merge(pt, [(tau, 1.0)], tmp_path / "m16.safetensors", dtype="float32", out_dtype="bf16")
    assert Checkpoint(low).specs["enc.weight"].dtype == "BF16"
    assert Checkpoint(low).specs["steps"].dtype == "I64"  # non-float tensors keep theirs
    torch.testing.assert_close(Checkpoint(low).get("enc.weight"), _weights(1, torch.bfloat16)["enc.weight"])


def test_prefix_key_map_strip_and_add(tmp_path):
    save_file(_weights(0), str(pt := tmp_path / "pt.safetensors"))
    save_file(_weights(1, prefix="model."), str(ft := tmp_path / "ft.safetensors"))
    with pytest.raises(VectorOpError, match="--strip-prefix / --add-prefix"):
        extract(pt, ft, tmp_path / "x.safetensors")
    v = extract(pt, ft, tmp_path / "v.safetensors", strip_prefix="model.")
    assert set(Checkpoint(v).keys()) == set(_weights(0))
    torch.testing.assert_close(
        Checkpoint(v).get("enc.bias"), _weights(0)["enc.bias"] - _weights(1)["enc.bias"]
    )
    w = extract(ft, pt, tmp_path / "w.safetensors", add_prefix="model.")  # the other way round
    assert set(Checkpoint(w).keys()) == set(_weights(0, prefix="model."))
    with pytest.raises(CheckpointError, match="--strip-prefix 'nope.' begins no tensor name"):
        merge(pt, [(v, 1.0)], tmp_path / "y.safetensors", strip_prefix="nope.")


def test_base_check_compares_tensor_content_not_layout(tmp_path):
    save_file(_weights(0), str(pt := tmp_path / "pt.safetensors"))
    folder = _folder(tmp_path / "pt_folder", _weights(0), "hf_sharded")  # the same weights, sharded
    save_file(_weights(1), str(ft := tmp_path / "ft.safetensors"))
    save_file(_weights(5), str(other := tmp_path / "other.safetensors"))
    g = extract(ft, pt, tmp_path / "g.safetensors", base=pt)
    merge(folder, [(g, 1.0)], tmp_path / "into_folder")  # the same base: accepted
    with pytest.raises(VectorOpError, match="pass --force to merge anyway"):
        merge(other, [(g, 1.0)], tmp_path / "refused.safetensors")
    assert Checkpoint(pt).content_sha256() == Checkpoint(folder).content_sha256()


# ---------------------------------------------------------------------------- 3. evaluate a folder
def test_evaluate_a_merged_folder_of_a_builtin_policy_and_refuse_an_unknown_type(tmp_path, monkeypatch):
    import prefect.artifacts

    from capvector.core.evaluation.rollouts import EvalConfig
    from capvector.tasks.steps import evaluation
    from capvector.tasks.trained_policy import resolve_checkpoints

    spec = {"type": "l1_chunk", "d_model": 16, "n_layers": 1, "n_heads": 2, "chunk_size": 2}
    files = {}
    for seed, name in enumerate(["pt", "ft", "ao"]):
        torch.manual_seed(seed)
        files[name] = save_policy(build_policy(spec, "cpu"), tmp_path / f"{name}.safetensors")
    base = tmp_path / "pt_folder"
    base.mkdir()
    shutil.copy(files["pt"], base / "model.safetensors")
    (base / "config.json").write_text(json.dumps(spec))
    gamma = extract(files["ao"], files["ft"], tmp_path / "gamma.safetensors")
    merged = merge(base, [(gamma, 1.0)], tmp_path / "merged", out_dtype="float32")
    assert load_policy(merged, "cpu").type_name == "l1_chunk"

    ws = Workspace(str(tmp_path / "home"))
    (checkpoint_id,) = resolve_checkpoints(ws, [str(merged)])
    monkeypatch.setattr(prefect.artifacts, "create_table_artifact", lambda **_: None)  # no Prefect API
    config = EvalConfig(tasks=["reach-v3"], episodes_per_task=1, horizon=5, execute_steps=2).model_dump()
    record = ws.api.get(evaluation.evaluate_checkpoint(ws, "eval", checkpoint_id, config))
    assert record.kind == "evaluation"

    unknown = _folder(tmp_path / "act", _weights(0), "lerobot")  # config.json names type "act"
    with pytest.raises(PolicyLoadError) as err:
        resolve_checkpoints(ws, [str(unknown)])
    line = str(err.value)
    assert "'act', which no installed package registers" in line and "own-checkpoints.md" in line
    assert "\n" not in line
    bare = tmp_path / "bare"
    bare.mkdir()
    save_file(_weights(0), str(bare / "model.safetensors"))
    with pytest.raises(PolicyLoadError, match="not a capvector policy.*own-checkpoints.md"):
        load_policy(bare, "cpu")
