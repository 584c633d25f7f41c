"""Streaming extract/merge/stats against a naive full-load implementation, and the bad-input errors."""

import json
import math
import os
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from capvector.core.policies.base import CONFIG_METADATA_KEY, build_policy, load_policy, save_policy
from capvector.core.vectors import vector_ops
from capvector.core.vectors.safetensors_io import Checkpoint, CheckpointError, write_checkpoint
from capvector.core.vectors.vector_ops import VectorOpError, extract, merge, select_names, stats


def _random_ckpt(dtype, seed, shift=0.0):
    g = torch.Generator().manual_seed(seed)
    return {
        "backbone.layers.0.weight": (torch.randn(32, 16, generator=g) + shift).to(dtype),
        "backbone.layers.0.bias": torch.randn(32, generator=g).to(dtype),
        "backbone.layers.1.weight": torch.randn(16, 32, generator=g).to(dtype),
        "head.proj.weight": torch.randn(4, 16, generator=g).to(dtype),
        "head.scale": torch.randn((), generator=g).to(dtype),
        "buffers.position_ids": torch.arange(10),
    }


def _write(tmp_path, name, tensors, sharded, metadata=None):
    if sharded:
        out = tmp_path / name
        write_checkpoint(out, tensors, metadata, max_shard_bytes=1500)
        assert len(Checkpoint(out).files) > 1
    else:
        out = tmp_path / f"{name}.safetensors"
        write_checkpoint(out, tensors, metadata)
    return out


def _load(path):
    c = Checkpoint(path)
    return {k: load_file(str(c.specs[k].file))[k] for k in c.keys()}


def _naive_sub(a, b):
    return {k: (a[k].float() - b[k].float()).to(a[k].dtype) if a[k].is_floating_point() else a[k] for k in a}


@pytest.mark.parametrize("sharded", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float16, torch.bfloat16])
def test_extract_and_merge_match_naive(tmp_path, dtype, sharded, monkeypatch):
    monkeypatch.setattr(vector_ops, "CHUNK_BYTES", 24)  # many pieces per tensor, odd boundaries
    pt, ft, ao = (_random_ckpt(dtype, s) for s in (0, 1, 2))
    p_pt, p_ft, p_ao = (_write(tmp_path, n, t, sharded) for n, t in (("pt", pt), ("ft", ft), ("ao", ao)))
    out_ext = tmp_path / ("gamma" if sharded else "gamma.safetensors")
    extract(p_ao, p_ft, out_ext, base=p_pt, max_shard_bytes=1500)
    gamma = _load(out_ext)
    want = _naive_sub(ao, ft)
    assert gamma.keys() == want.keys()
    for k in want:
        assert gamma[k].dtype == want[k].dtype and torch.equal(gamma[k], want[k]), k

    out_m = tmp_path / ("meta" if sharded else "meta.safetensors")
    merge(p_pt, [(out_ext, 1.1)], out_m, exclude=["head.*"], max_shard_bytes=1500)
    merged = _load(out_m)
    for k, v in pt.items():
        if v.is_floating_point() and not k.startswith("head."):
            expect = (v.float() + gamma[k].float() * 1.1).to(dtype)  # α·γ rounded, then added
        else:
            expect = v
        assert merged[k].dtype == v.dtype and torch.equal(merged[k], expect), k

    meta = Checkpoint(out_m).metadata
    inputs = json.loads(meta["capvector.inputs"])
    assert inputs["base"]["sha256"] == Checkpoint(p_pt).sha256()
    assert inputs["vector_0"]["sha256"] == Checkpoint(out_ext).sha256()
    assert json.loads(meta["capvector.coefficients"]) == [1.1]
    assert Checkpoint(out_ext).metadata["capvector.base_sha256"] == Checkpoint(p_pt).sha256()


def test_merge_several_vectors_and_single_file_readable_by_safetensors(tmp_path):
    pt, v1, v2 = (_random_ckpt(torch.float32, s) for s in (0, 1, 2))
    for t in (v1, v2):
        t["buffers.position_ids"] = pt["buffers.position_ids"]
    paths = [_write(tmp_path, n, t, False) for n, t in (("pt", pt), ("v1", v1), ("v2", v2))]
    out = tmp_path / "m.safetensors"
    merge(paths[0], [(paths[1], 0.5), (paths[2], -2.0)], out)
    got = load_file(out)
    for k in pt:
        if pt[k].is_floating_point():
            torch.testing.assert_close(got[k], pt[k] + 0.5 * v1[k] - 2.0 * v2[k], rtol=1e-6, atol=1e-6)


def test_key_shape_dtype_mismatches_write_nothing(tmp_path):
    a = _random_ckpt(torch.float32, 0)
    p_a = _write(tmp_path, "a", a, False)
    cases = {
        "missing": {k: v for k, v in a.items() if k != "head.scale"},
        "extra": {**a, "head.extra": torch.zeros(2)},
        "shape": {**a, "head.proj.weight": torch.zeros(4, 15)},
        "dtype": {**a, "head.proj.weight": a["head.proj.weight"].half()},
    }
    for case, t in cases.items():
        p_b = _write(tmp_path, case, t, False)
        with pytest.raises(VectorOpError) as e:
            extract(p_a, p_b, tmp_path / f"out_{case}.safetensors")
        assert "head." in str(e.value)
        with pytest.raises(VectorOpError):
            merge(p_a, [(p_b, 1.0)], tmp_path / f"merged_{case}")
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(("out_", "merged_", "."))) == []


@pytest.mark.parametrize("bad", [math.nan, math.inf])
@pytest.mark.parametrize("sharded", [False, True])
def test_non_finite_input_named_and_nothing_written(tmp_path, bad, sharded, monkeypatch):
    monkeypatch.setattr(vector_ops, "CHUNK_BYTES", 64)
    a, b = _random_ckpt(torch.bfloat16, 0), _random_ckpt(torch.bfloat16, 1)
    b["backbone.layers.1.weight"][3, 3] = bad
    p_a, p_b = _write(tmp_path, "a", a, sharded), _write(tmp_path, "b", b, sharded)
    before = set(tmp_path.iterdir())
    with pytest.raises(VectorOpError, match=r"backbone\.layers\.1\.weight.*subtrahend"):
        extract(p_a, p_b, tmp_path / "g", max_shard_bytes=1500)
    with pytest.raises(VectorOpError, match=r"backbone\.layers\.1\.weight"):
        merge(p_a, [(p_b, 1.0)], tmp_path / "m.safetensors")
    assert set(tmp_path.iterdir()) == before


def test_non_finite_coefficient_refused_before_anything_is_read(tmp_path):
    a = _write(tmp_path, "a", _random_ckpt(torch.float32, 0), False)
    for alpha in (math.nan, math.inf, -math.inf):
        with pytest.raises(VectorOpError, match=r"coefficients must be finite.*vector 1"):
            merge(a, [(a, 1.0), (a, alpha)], tmp_path / "m.safetensors")
    assert not (tmp_path / "m.safetensors").exists()


def test_float16_overflow_refused(tmp_path):
    a = {"w": torch.full((4,), 60000.0, dtype=torch.float16)}
    b = {"w": torch.full((4,), -60000.0, dtype=torch.float16)}
    p_a, p_b = _write(tmp_path, "a", a, False), _write(tmp_path, "b", b, False)
    with pytest.raises(VectorOpError, match="overflows"):
        extract(p_a, p_b, tmp_path / "g.safetensors")


def test_non_float_tensors_must_be_equal(tmp_path):
    a, b = _random_ckpt(torch.float32, 0), _random_ckpt(torch.float32, 1)
    b["buffers.position_ids"] = torch.arange(10) + 1
    p_a, p_b = _write(tmp_path, "a", a, False), _write(tmp_path, "b", b, False)
    with pytest.raises(VectorOpError, match="position_ids"):
        extract(p_a, p_b, tmp_path / "g.safetensors")


def test_filters(tmp_path):
    names = ["backbone.layers.0.weight", "backbone.layers.1.weight", "head.proj.weight"]
    assert select_names(names, include=["backbone.*"]) == names[:2]
    assert select_names(names, include=[r"re:backbone\.layers\.[1-9]\..*"]) == names[1:2]
    assert select_names(names, exclude=["*.proj.*"]) == names[:2]
    assert select_names(names, include=["proj.weight"]) == names[2:]  # trailing components, as LoRA targets
    assert select_names(names, exclude=["layers.1.*"]) == [names[0], names[2]]
    with pytest.raises(VectorOpError, match="match no tensor"):
        select_names(names, include=["encoder.*"])
    with pytest.raises(VectorOpError, match="selects no tensor"):
        select_names(names, include=["backbone.*"], exclude=["*weight"])
    a, b = _random_ckpt(torch.float32, 0), _random_ckpt(torch.float32, 1)
    p_a, p_b = _write(tmp_path, "a", a, False), _write(tmp_path, "b", b, False)
    with pytest.raises(VectorOpError, match="match no tensor"):
        extract(p_a, p_b, tmp_path / "g.safetensors", include=["nothing.*"])
    assert not (tmp_path / "g.safetensors").exists()


def test_partial_vector_and_wrong_base(tmp_path):
    pt, ft, ao, other = (_random_ckpt(torch.float32, s) for s in (0, 1, 2, 3))
    p_pt, p_ft, p_ao, p_other = (
        _write(tmp_path, n, t, False) for n, t in (("pt", pt), ("ft", ft), ("ao", ao), ("other", other))
    )
    g = tmp_path / "g.safetensors"
    extract(p_ao, p_ft, g, include=["backbone.*"], base=p_pt)
    assert Checkpoint(g).keys() == [k for k in pt if k.startswith("backbone.")]
    out = tmp_path / "m.safetensors"
    merge(p_pt, [(g, 1.0)], out)
    got = load_file(out)
    assert torch.equal(got["head.proj.weight"], pt["head.proj.weight"])
    torch.testing.assert_close(
        got["backbone.layers.0.weight"],
        pt["backbone.layers.0.weight"] + ao["backbone.layers.0.weight"] - ft["backbone.layers.0.weight"],
    )
    with pytest.raises(VectorOpError, match="--force"):
        merge(p_other, [(g, 1.0)], tmp_path / "wrong.safetensors")
    assert not (tmp_path / "wrong.safetensors").exists()
    merge(p_other, [(g, 1.0)], tmp_path / "forced.safetensors", force=True)
    # a full (non-partial) vector must cover every tensor of base
    bigger = _write(tmp_path, "big", {**pt, "extra.w": torch.zeros(3)}, False)
    with pytest.raises(VectorOpError, match="missing from vector 0"):
        merge(bigger, [(p_ao, 1.0)], tmp_path / "x.safetensors")


def test_missing_shard_and_truncated_file(tmp_path):
    a = _random_ckpt(torch.float32, 0)
    sharded = _write(tmp_path, "sh", a, True)
    victim = Checkpoint(sharded).files[-1]
    single = _write(tmp_path, "one", a, False)
    raw = single.read_bytes()
    (tmp_path / "trunc.safetensors").write_bytes(raw[:-10])
    (tmp_path / "short.safetensors").write_bytes(raw[:5])
    with pytest.raises(CheckpointError, match="truncated"):
        Checkpoint(tmp_path / "trunc.safetensors")
    with pytest.raises(CheckpointError, match="truncated"):
        Checkpoint(tmp_path / "short.safetensors")
    with pytest.raises(CheckpointError, match="truncated"):
        extract(tmp_path / "trunc.safetensors", single, tmp_path / "g.safetensors")
    victim.unlink()
    with pytest.raises(CheckpointError, match=f"missing shard.*{victim.name}"):
        merge(sharded, [(single, 1.0)], tmp_path / "m")
    assert not (tmp_path / "g.safetensors").exists() and not (tmp_path / "m").exists()


def test_reads_checkpoints_written_by_safetensors(tmp_path):
    a, b = _random_ckpt(torch.float16, 0), _random_ckpt(torch.float16, 1)
    save_file(a, tmp_path / "a.safetensors")
    save_file(b, tmp_path / "b.safetensors")
    extract(tmp_path / "a.safetensors", tmp_path / "b.safetensors", tmp_path / "g.safetensors")
    got = load_file(tmp_path / "g.safetensors")
    for k, v in _naive_sub(a, b).items():
        assert torch.equal(got[k], v)


def test_stats_against_hand_computation(tmp_path):
    base, v, ref = (_random_ckpt(torch.float32, s) for s in (0, 1, 2))
    p_base, p_v, p_ref = (_write(tmp_path, n, t, False) for n, t in (("b", base), ("v", v), ("r", ref)))
    rows = stats(p_v, base=p_base, reference_vector=p_ref, group_depth=1)
    by = {(r.level, r.name): r for r in rows}
    k = "head.proj.weight"
    g, w, r = v[k].double(), base[k].double(), ref[k].double()
    row = by[("tensor", k)]
    assert row.l2 == pytest.approx(g.norm().item())
    assert row.relative_norm == pytest.approx((g.norm() / w.norm()).item())
    assert row.cosine == pytest.approx(
        torch.nn.functional.cosine_similarity(g.flatten(), r.flatten(), 0).item()
    )
    assert row.sign_agreement == pytest.approx((torch.sign(g) == torch.sign(r)).double().mean().item())
    head = [n for n in v if n.startswith("head.")]
    gh = torch.cat([v[n].double().flatten() for n in head])
    rh = torch.cat([ref[n].double().flatten() for n in head])
    grp = by[("group", "head")]
    assert grp.numel == gh.numel() and grp.l2 == pytest.approx(gh.norm().item())
    assert grp.cosine == pytest.approx(torch.nn.functional.cosine_similarity(gh, rh, 0).item())
    assert ("all", "*") in by and ("tensor", "buffers.position_ids") not in by
    assert all(isinstance(r.model_dump(), dict) for r in rows)


def test_merged_policy_loads_as_a_policy(tmp_path):
    """`vector merge` output keeps base's policy config: load_policy gives θ_pt + α·(θ_ao − θ_ft)."""
    config = {"type": "l1_chunk", "d_model": 32, "n_layers": 2, "n_heads": 2, "chunk_size": 4}
    paths = {}
    for seed, role in enumerate(("pt", "ft", "ao")):
        torch.manual_seed(seed)
        paths[role] = save_policy(build_policy(config, device="cpu"), tmp_path / f"{role}.safetensors")
    gamma = extract(paths["ao"], paths["ft"], tmp_path / "g.safetensors", base=paths["pt"])
    merged = merge(paths["pt"], [(gamma, 1.5)], tmp_path / "merged.safetensors")
    meta = Checkpoint(merged).metadata
    assert vector_ops.CARRIED_KEYS == (CONFIG_METADATA_KEY,)
    assert meta[CONFIG_METADATA_KEY] == Checkpoint(paths["pt"]).metadata[CONFIG_METADATA_KEY]
    assert meta["capvector.kind"] == "merged"
    policy = load_policy(merged, device="cpu")
    pt, ft, ao = (load_file(str(paths[r])) for r in ("pt", "ft", "ao"))
    state = policy.state_dict()
    assert state.keys() == pt.keys()
    for k, v in pt.items():
        want = v + 1.5 * (ao[k] - ft[k]) if v.is_floating_point() else v
        torch.testing.assert_close(state[k], want, rtol=1e-6, atol=1e-6)


# ---------------------------------------------------------------------------- reproducible bytes
@pytest.mark.parametrize("sharded", [False, True])
def test_outputs_name_inputs_by_digest_only_so_any_folder_gives_the_same_bytes(tmp_path, sharded):
    """The same inputs read from two homes (or a store and a user's folder) give one output, byte for
    byte: `capvector.inputs` holds digests, never a path, so the output's content id is the same."""
    pt, ft, ao = (_random_ckpt(torch.float32, s) for s in (0, 1, 2))
    outs = {}
    for home in ("home_a", "home_b"):
        root = tmp_path / home / "store" / "objects"
        root.mkdir(parents=True)
        p_pt, p_ft, p_ao = (_write(root, n, t, sharded) for n, t in (("pt", pt), ("ft", ft), ("ao", ao)))
        g = extract(p_ao, p_ft, root / "gamma.safetensors", base=p_pt)
        m = merge(p_pt, [(g, 1.1)], root / ("meta" if sharded else "meta.safetensors"), max_shard_bytes=1500)
        outs[home] = (g, m)
        for out in (g, m):
            meta = Checkpoint(out).metadata
            assert all(str(tmp_path) not in v for v in meta.values()), meta
            inputs = json.loads(meta["capvector.inputs"])
            assert all(set(entry) == {"sha256"} for entry in inputs.values()), inputs
    for a, b in zip(outs["home_a"], outs["home_b"], strict=True):
        assert Checkpoint(a).sha256() == Checkpoint(b).sha256()
        assert [f.read_bytes() for f in Checkpoint(a).files] == [f.read_bytes() for f in Checkpoint(b).files]


# ---------------------------------------------------------------------------- the vector commands
def _count(workspace) -> int:
    return int(workspace.api.query("SELECT count(*) AS n FROM artifacts")["n"][0])


@pytest.fixture
def user(tmp_path):
    """A user's folder of checkpoints (θ_pt, θ_ft, θ_ao and broken ones) and an empty home."""
    from capvector.tasks.runtime.workspace import Workspace

    folder = tmp_path / "user"
    folder.mkdir()
    pt, ft, ao = (_random_ckpt(torch.float32, s) for s in (0, 1, 2))
    nan = {**ao, "head.proj.weight": ao["head.proj.weight"].clone()}
    nan["head.proj.weight"][1, 2] = math.nan
    missing = {k: v for k, v in pt.items() if k != "head.scale"}
    paths = {n: _write(folder, n, t, False) for n, t in [("pt", pt), ("ft", ft), ("ao", ao), ("nan", nan),
                                                          ("missing", missing)]}  # fmt: skip
    return Workspace(str(tmp_path / "home")), folder, paths


def test_failed_vector_commands_register_none_of_their_inputs(user):
    from capvector.tasks.vector_commands import extract_cli, merge_cli, stats_cli

    workspace, folder, p = user
    before = sorted(folder.iterdir())
    with pytest.raises(VectorOpError, match="NaN"):  # a value error, found while streaming
        extract_cli(
            workspace, str(p["nan"]), str(p["ft"]), folder / "g.safetensors", str(p["pt"]), None, None
        )
    assert _count(workspace) == 0  # θ_pt, θ_ft were fine, but nothing was made from them
    with pytest.raises(VectorOpError, match="NaN"):
        merge_cli(
            workspace, str(p["pt"]), [(str(p["nan"]), 1.0)], folder / "m.safetensors", None, None, False
        )
    with pytest.raises(VectorOpError, match="head.scale"):  # a structural error, found before
        merge_cli(workspace, str(p["missing"]), [(str(p["ft"]), 1.0)], folder / "m2", None, None, False)
    with pytest.raises(VectorOpError, match="head.scale"):
        stats_cli(workspace, str(p["ft"]), str(p["missing"]), None)
    with pytest.raises(ValueError, match="alpha.*finite"):
        merge_cli(workspace, str(p["pt"]), [(str(p["ft"]), math.nan)], folder / "m3", None, None, False)
    assert _count(workspace) == 0
    assert sorted(folder.iterdir()) == before  # no output, no temporary file


def test_vector_commands_register_inputs_and_output_once_they_succeed(user):
    from capvector.tasks.vector_commands import extract_cli, stats_cli

    workspace, folder, p = user
    out = folder / "gamma.safetensors"
    record = extract_cli(workspace, str(p["ao"]), str(p["ft"]), out, str(p["pt"]), None, None)
    assert record.id == Checkpoint(out).sha256()
    parents = {r.role: r.id for r in record.parents}
    assert parents == {role: Checkpoint(p[n]).sha256() for role, n in
                       [("minuend", "ao"), ("subtrahend", "ft"), ("base", "pt")]}  # fmt: skip
    stats_cli(workspace, str(out), str(p["pt"]), None)
    assert _count(workspace) == 5  # θ_ao, θ_ft, θ_pt, γ, its statistics
    assert sorted(x.name for x in folder.iterdir() if x.name.startswith(".")) == []


@pytest.mark.parametrize("sharded", [False, True])
def test_identical_rerun_registers_an_output_written_but_never_registered(user, sharded):
    """Killed between writing `-o` and registering it: the same command again registers that output."""
    from capvector.tasks.runtime.workspace import Workspace
    from capvector.tasks.vector_commands import extract_cli, merge_cli

    workspace, folder, p = user
    out = folder / ("gamma" if sharded else "gamma.safetensors")
    # what the killed command had written (a folder output carries the command's model card)
    extract_cli(
        Workspace(str(folder.parent / "elsewhere")), str(p["ao"]), str(p["ft"]), out, str(p["pt"]), None, None
    )
    mtime = out.stat().st_mtime_ns
    record = extract_cli(workspace, str(p["ao"]), str(p["ft"]), out, str(p["pt"]), None, None)
    assert out.stat().st_mtime_ns == mtime  # left as it was
    stored = Checkpoint(workspace.path(record.id))
    assert [f.read_bytes() for f in stored.files] == [f.read_bytes() for f in Checkpoint(out).files]

    merged = folder / "merged.safetensors"
    merge(p["pt"], [(out, 1.1)], merged)
    again = merge_cli(workspace, str(p["pt"]), [(record.id, 1.1)], merged, None, None, False)
    assert again.id == Checkpoint(merged).sha256()


def test_an_existing_output_with_other_bytes_is_still_refused(user):
    from capvector.tasks.vector_commands import extract_cli

    workspace, folder, p = user
    out = folder / "gamma.safetensors"
    extract(p["ao"], p["ft"], out, include=["backbone.*"])  # another vector at that path
    kept = out.read_bytes()
    with pytest.raises(FileExistsError, match="already exists"):
        extract_cli(workspace, str(p["ao"]), str(p["ft"]), out, None, None, None)
    (folder / "junk.safetensors").write_bytes(b"keep me")
    with pytest.raises(FileExistsError, match="already exists"):
        extract_cli(workspace, str(p["ao"]), str(p["ft"]), folder / "junk.safetensors", None, None, None)
    assert out.read_bytes() == kept and (folder / "junk.safetensors").read_bytes() == b"keep me"
    assert _count(workspace) == 0
    assert sorted(x.name for x in folder.iterdir() if x.name.startswith(".")) == []


@pytest.mark.parametrize("sharded", [False, True])
def test_a_command_killed_while_writing_leaves_nothing_in_the_users_folder(user, sharded):
    """SIGKILL in the middle of streaming: no temporary file or folder beside `-o`."""
    import subprocess
    import sys

    workspace, folder, p = user
    out = folder / ("gamma" if sharded else "gamma.safetensors")
    before = sorted(folder.iterdir())
    code = f"""
import os, sys
sys.path.insert(0, {str(Path(__file__).resolve().parent.parent)!r})
from capvector.core.vectors import vector_ops
from capvector.tasks.vector_commands import extract_cli
from capvector.tasks.runtime.workspace import Workspace
from pathlib import Path

calls = []
real = vector_ops._cast_back
def dying(*args):
    calls.append(1)
    if len(calls) == 3:
        os.kill(os.getpid(), 9)
    return real(*args)
vector_ops._cast_back = dying
ws = Workspace({workspace.home!r})
extract_cli(ws, {str(p["ao"])!r}, {str(p["ft"])!r}, Path({str(out)!r}), None, None, None)
"""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == -9, proc.stderr
    assert sorted(folder.iterdir()) == before


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_null_vector_keeps_each_tensors_norm_in_a_random_direction(tmp_path, dtype):
    gamma = _write(tmp_path, "gamma", _random_ckpt(dtype, 0), sharded=False)
    first = vector_ops.null_vector(gamma, tmp_path / "null0.safetensors", seed=0)
    again = vector_ops.null_vector(gamma, tmp_path / "null0b.safetensors", seed=0)
    other = vector_ops.null_vector(gamma, tmp_path / "null1.safetensors", seed=1)
    g, n0, n0b, n1 = (_load(p) for p in (gamma, first, again, other))
    assert set(n0) == set(g)
    tolerance = 1e-5 if dtype == torch.float32 else 1e-2  # bf16 rounding of each element
    for name, t in g.items():
        if not t.is_floating_point():
            assert torch.equal(n0[name], t)  # non-float tensors are carried as they are
            continue
        a, b = t.double().flatten(), n0[name].double().flatten()
        assert abs(b.norm() - a.norm()) <= tolerance * a.norm()
        assert torch.equal(n0[name], n0b[name])  # the seed decides it
        if a.numel() > 1:
            assert not torch.equal(n0[name], n1[name])
            assert abs(torch.nn.functional.cosine_similarity(a, b, dim=0)) < 0.5  # not γ's direction


# ---------------------------------------------------------------------------- stats, streamed
def _whole_tensor_stats(v, base, ref):
    """`stats`' per-tensor sums as they were computed before streaming: whole tensors in float64."""
    out = {}
    for k, g in v.items():
        if not g.is_floating_point():
            continue
        g, w, r = (t[k].double().flatten().numpy() for t in (v, base, ref))
        sg, sr = np.sign(g), np.sign(r)
        both = (sg != 0) & (sr != 0)
        out[k] = {
            "numel": g.size,
            "l2": math.sqrt(g @ g),
            "base_l2": math.sqrt(w @ w),
            "cosine": (g @ r) / math.sqrt((g @ g) * (r @ r)),
            "sign_agreement": ((sg == sr) & both).sum() / both.sum(),
        }
    return out


@pytest.mark.parametrize("chunk", [24, 4096, vector_ops.CHUNK_BYTES])
def test_streamed_stats_equal_the_whole_tensor_computation(tmp_path, chunk, monkeypatch):
    """Pieces of `CHUNK_BYTES` give the whole-tensor values up to float rounding, across dtypes (the base
    in another dtype than the vector: pieces are counted in elements), with zeros in the sign counts."""
    monkeypatch.setattr(vector_ops, "CHUNK_BYTES", chunk)
    g = torch.Generator().manual_seed(0)

    def ckpt(dtype):
        t = _random_ckpt(dtype, int(torch.randint(100, (), generator=g)))
        t["big.weight"] = torch.randn(1200, 7, generator=g).to(dtype)  # 8400 elements: several pieces
        t["big.weight"][torch.rand(1200, 7, generator=g) < 0.2] = 0
        return t

    v, base, ref = ckpt(torch.bfloat16), ckpt(torch.float32), ckpt(torch.float16)
    paths = [_write(tmp_path, n, t, False) for n, t in (("v", v), ("b", base), ("r", ref))]
    rows = stats(*paths)
    want = _whole_tensor_stats(v, base, ref)
    got = {r.name: r for r in rows if r.level == "tensor"}
    assert got.keys() == want.keys()
    for k, w in want.items():
        assert got[k].numel == w["numel"]
        for field in ("l2", "base_l2", "cosine", "sign_agreement"):
            assert getattr(got[k], field) == pytest.approx(w[field], rel=1e-12, abs=1e-15), (k, field)
    total = next(r for r in rows if r.level == "all")
    assert total.numel == sum(w["numel"] for w in want.values())
    assert total.l2 == pytest.approx(math.sqrt(sum(w["l2"] ** 2 for w in want.values())), rel=1e-12)


def test_stats_memory_does_not_grow_with_the_tensor(tmp_path, monkeypatch):
    """Tensors 128 pieces long: the peak of traced allocations (numpy's buffers included) stays a few
    pieces (1.1 MiB measured), far below one tensor (the whole-tensor float64 version: 84 MiB here)."""
    monkeypatch.setattr(vector_ops, "CHUNK_BYTES", 64 << 10)
    g = torch.Generator().manual_seed(0)
    tensors = [{"w": torch.randn(1 << 21, generator=g)} for _ in range(3)]  # 8 MiB of float32 each
    paths = [_write(tmp_path, n, t, False) for n, t in zip(("v", "b", "r"), tensors, strict=True)]
    tracemalloc.start()
    try:
        rows = stats(*paths)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert rows[0].numel == 1 << 21 and rows[0].cosine is not None
    assert peak < 4 << 20, f"peak {peak / 2**20:.1f} MiB for 8 MiB tensors read in 64 KiB pieces"


THREADED = """
import hashlib, json, sys
import torch
torch.set_num_threads(int(sys.argv[1]))
from capvector.core.vectors import vector_ops
v, base, ref, null = sys.argv[2:6]
rows = vector_ops.stats(v, base=base, reference_vector=ref)
vector_ops.null_vector(v, null, seed=3)
print(json.dumps([r.model_dump() for r in rows], sort_keys=True))
print(hashlib.sha256(open(null, "rb").read()).hexdigest())
"""


def test_stats_and_null_vector_bytes_do_not_depend_on_the_thread_count(tmp_path):
    """The `vector_stats` of γ had one id in the step pool and another on a Dask worker (whose nanny
    sets one BLAS/OpenMP thread): its sums were BLAS dots, whose order of additions follows the thread
    count. The stats and the null vector (scaled by such a sum) are the same bytes with 1 or 2 threads."""
    import subprocess
    import sys

    gen = torch.Generator().manual_seed(0)
    paths = []
    for name in ("v", "base", "ref"):  # over OpenBLAS's 10,000 elements, below which a dot is serial
        t = {"blocks.0.w": torch.randn(300_000, generator=gen), "head.b": torch.randn(7, generator=gen)}
        save_file(t, tmp_path / f"{name}.safetensors")
        paths.append(str(tmp_path / f"{name}.safetensors"))
    out = {}
    for n in (1, 2):
        env = {
            **os.environ,
            "OMP_NUM_THREADS": str(n),
            "OPENBLAS_NUM_THREADS": str(n),
            "MKL_NUM_THREADS": str(n),
        }
        null = str(tmp_path / f"null{n}.safetensors")
        proc = subprocess.run(
            [sys.executable, "-c", THREADED, str(n), *paths, null],
            capture_output=True,
            text=True,
            env=env,
            cwd=Path(__file__).resolve().parent.parent,
        )
        assert proc.returncode == 0, proc.stderr[-2000:]
        out[n] = proc.stdout
    assert out[1] == out[2]
