"""`vector_ops.mean` and `capvector vector mean`: the mean of K seed draws of a capability vector (and
their TIES merge), streamed; the denoising law cos(γ̄_K, s) = sqrt(Kρ / (Kρ + 1 − ρ)), TIES against a
hand computation and a plain numpy one, the CLI's registration and lineage, and the refusals."""

import json
import math
import os
import shutil
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import run_cli
from typer.testing import CliRunner

from capvector.core.vectors import vector_ops
from capvector.core.vectors.safetensors_io import Checkpoint, write_checkpoint
from capvector.core.vectors.vector_ops import VectorOpError, extract, mean
from capvector.flows.cli.main import app
from capvector.tasks.runtime.workspace import Workspace
from capvector.tasks.vector_commands import mean_cli


def _write(folder: Path, name: str, tensors: dict, sharded: bool = False, metadata=None) -> Path:
    if sharded:
        out = folder / name
        write_checkpoint(out, tensors, metadata, max_shard_bytes=100)
        assert len(Checkpoint(out).files) > 1
        return out
    out = folder / f"{name}.safetensors"
    write_checkpoint(out, tensors, metadata)
    return out


def _load(path: Path) -> dict:
    c = Checkpoint(path)
    return {k: c.get(k) for k in c.keys()}


def _cos(a: np.ndarray, b: np.ndarray) -> float:
    return float(a @ b / math.sqrt((a @ a) * (b @ b)))


# ---------------------------------------------------------------------------------------- the mean
def test_the_mean_of_k_draws_approaches_the_signal_as_predicted(tmp_path, monkeypatch):
    """γ_d = s + noise_d, 200k entries, signal fraction ρ = 0.2 (var s = ρ, var noise = 1 − ρ): one draw
    is at cos sqrt(ρ) ≈ 0.45 from s, two draws at cos ≈ ρ from each other, and the streamed mean of K
    at sqrt(Kρ / (Kρ + 1 − ρ)) (0.75 for K = 4, 0.90 for 16). The sampling error of these cosines is
    about 0.002 here; the tolerance is 0.02."""
    monkeypatch.setattr(vector_ops, "CHUNK_BYTES", 64 << 10)  # several pieces per tensor
    rho, shapes = 0.2, {"blocks.0.w": (200, 500), "blocks.1.w": (100_000,)}
    rng = np.random.default_rng(0)
    d = sum(math.prod(s) for s in shapes.values())
    signal = rng.normal(0, math.sqrt(rho), d).astype(np.float32)
    draws = []
    for i in range(16):
        g = signal + rng.normal(0, math.sqrt(1 - rho), d).astype(np.float32)
        parts, at = {}, 0
        for name, shape in shapes.items():
            n = math.prod(shape)
            parts[name] = torch.from_numpy(g[at : at + n].reshape(shape).copy())
            at += n
        draws.append(_write(tmp_path, f"gamma_{i}", parts))

    def flat(path: Path) -> np.ndarray:
        got = _load(path)
        return np.concatenate([got[n].numpy().reshape(-1) for n in shapes]).astype(np.float64)

    first = flat(draws[0])
    assert _cos(first, flat(draws[1])) == pytest.approx(rho, abs=0.02)  # the estimator of ρ
    for k in (1, 4, 16):
        predicted = math.sqrt(k * rho / (k * rho + 1 - rho))
        got = first if k == 1 else flat(mean(draws[:k], tmp_path / f"mean_{k}.safetensors"))
        assert _cos(got, signal.astype(np.float64)) == pytest.approx(predicted, abs=0.02), k


@pytest.mark.parametrize("sharded", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float16, torch.bfloat16])
def test_mean_matches_a_plain_torch_mean(tmp_path, dtype, sharded, monkeypatch):
    """Summed in float32 in input order, divided by K, rounded to the dtype: what torch does in that
    order. Non-float tensors equal in every input are carried over."""
    monkeypatch.setattr(vector_ops, "CHUNK_BYTES", 40)  # many pieces per tensor, odd boundaries
    g = torch.Generator().manual_seed(0)
    shapes = {"a.weight": (8, 6), "a.bias": (8,), "b.weight": (5, 8), "scale": ()}
    vecs = [{k: torch.randn(s, generator=g).to(dtype) for k, s in shapes.items()} for _ in range(3)]
    for v in vecs:
        v["buffers.ids"] = torch.arange(7)
    paths = [_write(tmp_path, f"v{i}", v, sharded) for i, v in enumerate(vecs)]
    out = mean(paths, tmp_path / ("m" if sharded else "m.safetensors"), max_shard_bytes=100)
    got = _load(out)
    assert got.keys() == vecs[0].keys()
    for k, v in vecs[0].items():
        if v.is_floating_point():
            acc = v.float()
            for other in vecs[1:]:
                acc = acc + other[k].float()
            want = (acc / 3).to(dtype)
        else:
            want = v
        assert got[k].dtype == want.dtype and torch.equal(got[k], want), k


def test_the_output_names_every_input_by_digest(tmp_path):
    base = _write(tmp_path, "pt", {"w": torch.zeros(4), "b": torch.zeros(2)})
    vecs = []
    for i in range(3):
        ao = _write(tmp_path, f"ao{i}", {"w": torch.randn(4), "b": torch.randn(2)})
        ft = _write(tmp_path, f"ft{i}", {"w": torch.randn(4), "b": torch.randn(2)})
        vecs.append(extract(ao, ft, tmp_path / f"g{i}.safetensors", include=["w"], base=base))
    out = mean(vecs, tmp_path / "m.safetensors")
    meta = Checkpoint(out).metadata
    inputs = json.loads(meta["capvector.inputs"])
    assert inputs == {f"vector_{i}": {"sha256": Checkpoint(v).sha256()} for i, v in enumerate(vecs)}
    assert meta["capvector.kind"] == "vector" and meta["capvector.method"] == "mean"
    assert json.loads(meta["capvector.coefficients"]) == [1 / 3] * 3
    assert meta["capvector.base_sha256"] == Checkpoint(base).sha256()  # the base they share
    shared = Checkpoint(vecs[0]).metadata["capvector.base_content_sha256"]
    assert meta["capvector.base_content_sha256"] == shared  # so `merge` accepts it on the same weights
    assert json.loads(meta["capvector.exclude"]) == []  # the filter they share, not a base hash
    assert json.loads(meta["capvector.partial"]) is True and json.loads(meta["capvector.include"]) == ["w"]
    assert str(tmp_path) not in json.dumps(meta)  # digests only: the same bytes from any folder
    other = _write(tmp_path, "other_pt", {"w": torch.ones(4), "b": torch.ones(2)})
    stranger = extract(vecs[0], vecs[1], tmp_path / "s.safetensors", base=other)
    with pytest.raises(VectorOpError, match="different bases"):
        mean([vecs[0], stranger], tmp_path / "x.safetensors")
    assert not (tmp_path / "x.safetensors").exists()


def test_mean_memory_does_not_grow_with_k_or_the_tensor(tmp_path, monkeypatch):
    """8 vectors of one 8 MiB tensor each, read in 64 KiB pieces: the traced peak stays a few pieces
    per input (the whole-checkpoint alternative holds 64 MiB); TIES's threshold passes included."""
    monkeypatch.setattr(vector_ops, "CHUNK_BYTES", 64 << 10)
    g = torch.Generator().manual_seed(0)
    paths = [_write(tmp_path, f"v{i}", {"w": torch.randn(1 << 21, generator=g)}) for i in range(8)]
    for method in ("mean", "ties"):
        tracemalloc.start()
        try:
            mean(paths, tmp_path / f"{method}.safetensors", method=method)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert peak < 8 << 20, f"{method}: peak {peak / 2**20:.1f} MiB for 8 × 8 MiB in 64 KiB pieces"


# ---------------------------------------------------------------------------------------------- TIES
def _ties_numpy(vectors: list[np.ndarray], density: float) -> np.ndarray:
    """TIES on whole float64 arrays, as written down (the reference the streamed version must equal)."""
    kept = []
    for v in vectors:
        k = math.ceil(round(density * v.size, 9))
        limit = np.sort(np.abs(v))[v.size - k] if v.size else 0
        kept.append(np.where(np.abs(v) >= limit, v, 0))
    kept = np.stack(kept)
    sign = np.sign(kept.sum(0))
    agree = (np.sign(kept) == sign) & (sign != 0)
    count = agree.sum(0)
    return np.where(count > 0, (kept * agree).sum(0) / np.maximum(count, 1), 0)


def test_ties_matches_the_hand_computation(tmp_path):
    """density 0.4 of 5 entries: each vector keeps its 2 largest magnitudes (more on a tie).
    v0 = [ 3, -1, 0,   2,  2]  keeps 3, 2, 2 (three tied at the 2nd largest magnitude, 2)
    v1 = [-4,  1, 1,   0,  5]  keeps -4, 5
    v2 = [ 1, -3, 0.5, -2, 0]  keeps -3, -2
    sums of what is kept: [-1, -3, 0, 0, 7]: signs -, -, none (nothing kept), none (2 − 2: a tie), +
    result: [-4 (3 disagrees), -3, 0, 0 (mergekit: +2), mean(2, 5) = 3.5]
    A one-entry tensor keeps its entry (⌈0.4⌉ = 1): [2], [-1], [-3] -> mean(-1, -3) = -2.
    A vector that is 0 in a tensor takes no part in its election or its mean: [0, 0], [1, -6], [3, -2]
    keep (all of v0, zeros), -6, 3 -> [3, -6]."""
    vs = [
        {"t": [3.0, -1, 0, 2, 2], "one": [2.0], "z": [0.0, 0]},
        {"t": [-4.0, 1, 1, 0, 5], "one": [-1.0], "z": [1.0, -6]},
        {"t": [1.0, -3, 0.5, -2, 0], "one": [-3.0], "z": [3.0, -2]},
    ]
    paths = [_write(tmp_path, f"v{i}", {k: torch.tensor(x) for k, x in v.items()}) for i, v in enumerate(vs)]
    got = _load(mean(paths, tmp_path / "t.safetensors", method="ties", density=0.4))
    assert got["t"].tolist() == [-4, -3, 0, 0, 3.5]
    assert got["one"].tolist() == [-2]
    assert got["z"].tolist() == [3, -6]  # ⌈0.8⌉ = 1 kept of each: nothing of v0 (0 is 0), -6, 3
    meta = Checkpoint(tmp_path / "t.safetensors").metadata
    assert meta["capvector.method"] == "ties" and json.loads(meta["capvector.density"]) == 0.4
    assert "capvector.coefficients" not in meta  # not a linear combination
    assert got["t"].tolist() == _ties_numpy([np.array(v["t"], float) for v in vs], 0.4).tolist()


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.float16, torch.bfloat16])
def test_streamed_ties_equals_whole_array_ties(tmp_path, dtype, monkeypatch):
    """The threshold found piece by piece (a radix selection over the magnitude's bits: 1 pass for
    16-bit floats, 2 for float32, 4 for float64) equals the one found on the whole tensor, with ties at
    the threshold (values repeated on purpose) and exact zeros; and TIES is odd: ties(−v) = −ties(v)."""
    g = torch.Generator().manual_seed(1)
    shapes = {"a": (40, 25), "b": (333,), "c": (7,)}
    vecs = []
    for _ in range(5):
        v = {k: torch.randn(s, generator=g) for k, s in shapes.items()}
        v["a"].view(-1)[::7] = torch.randn(1, generator=g)  # one magnitude many times over
        v["b"][::5] = 0.0
        vecs.append({k: x.to(dtype) for k, x in v.items()})
    paths = [_write(tmp_path, f"v{i}", v) for i, v in enumerate(vecs)]
    negated = [_write(tmp_path, f"n{i}", {k: -x for k, x in v.items()}) for i, v in enumerate(vecs)]
    whole = _load(mean(paths, tmp_path / "whole.safetensors", method="ties", density=0.3))
    monkeypatch.setattr(vector_ops, "CHUNK_BYTES", 64)  # every tensor in many pieces
    pieces = _load(mean(paths, tmp_path / "pieces.safetensors", method="ties", density=0.3))
    flipped = _load(mean(negated, tmp_path / "flipped.safetensors", method="ties", density=0.3))
    for k in shapes:
        want = _ties_numpy([v[k].double().numpy().reshape(-1) for v in vecs], 0.3)
        assert torch.equal(whole[k], pieces[k]), k
        assert torch.equal(flipped[k], -whole[k]), k
        ref = torch.from_numpy(want.reshape(shapes[k])).to(dtype)
        torch.testing.assert_close(whole[k], ref)  # the dtype's tolerance: sums in float32 vs float64


def test_ties_refuses_non_finite_values(tmp_path, monkeypatch):
    """A NaN compares as neither sign: TIES would drop it silently where a mean propagates it."""
    monkeypatch.setattr(vector_ops, "CHUNK_BYTES", 32)
    a = {"w": torch.randn(20)}
    b = {"w": torch.randn(20)}
    b["w"][13] = math.nan
    paths = [_write(tmp_path, "a", a), _write(tmp_path, "b", b)]
    for method in ("mean", "ties"):
        with pytest.raises(VectorOpError, match=r"NaN or Inf in tensor 'w' of vector 1"):
            mean(paths, tmp_path / f"{method}.safetensors", method=method)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.safetensors", "b.safetensors"]


# ------------------------------------------------------------------------------------------ refusals
def test_mismatched_inputs_are_named_and_nothing_is_written(tmp_path):
    a = {"x.weight": torch.randn(4, 3), "x.bias": torch.randn(4), "ids": torch.arange(3)}
    pa, pb = _write(tmp_path, "a", a), _write(tmp_path, "b", {k: v.clone() for k, v in a.items()})
    # each message names the tensor and the file (each case's file is called after the case)
    cases = {
        "missing": (
            {k: v for k, v in a.items() if k != "x.bias"},
            r"missing from vector 2 .*missing.*'x\.bias'",
        ),
        "extra": ({**a, "y.weight": torch.zeros(2)}, r"unexpected tensor.* in vector 2 .*extra.*'y\.weight'"),
        "shape": ({**a, "x.bias": torch.zeros(5)}, r"vector 2 .*shape.*x\.bias \(F32\[4\] vs F32\[5\]"),
        "dtype": ({**a, "x.bias": a["x.bias"].half()}, r"vector 2 .*dtype.*x\.bias \(F32\[4\] vs F16"),
        "ids": (
            {**a, "ids": torch.arange(3) + 1},
            r"non-float tensor 'ids' differs between vector 0 and vector 2",
        ),
    }
    for case, (tensors, message) in cases.items():
        bad = _write(tmp_path, case, tensors)
        for method in ("mean", "ties"):
            with pytest.raises(VectorOpError, match=message):
                mean([pa, pb, bad], tmp_path / f"out_{case}_{method}.safetensors", method=method)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(("out_", "."))]


def test_bad_arguments_are_refused_before_anything_is_read(tmp_path):
    pa = _write(tmp_path, "a", {"w": torch.randn(3)})
    pb = _write(tmp_path, "b", {"w": torch.randn(3)})
    with pytest.raises(VectorOpError, match="at least 2 vectors, got 1"):
        mean([pa], tmp_path / "m.safetensors")
    with pytest.raises(VectorOpError, match="method must be one of mean, ties"):
        mean([pa, pb], tmp_path / "m.safetensors", method="median")
    for density in (0, -0.1, 1.5, math.nan):
        with pytest.raises(VectorOpError, match=r"density must be a number in \(0, 1\]"):
            mean([pa, pb], tmp_path / "m.safetensors", method="ties", density=density)
    with pytest.raises(VectorOpError, match="vector 0 and vector 2 are the same checkpoint"):
        mean([pa, pb, f"{tmp_path}/./a.safetensors"], tmp_path / "m.safetensors")
    shutil.copy(pa, tmp_path / "a_copy.safetensors")  # the same bytes under another name
    with pytest.raises(VectorOpError, match="vector 0 and vector 2 are the same bytes"):
        mean([pa, pb, tmp_path / "a_copy.safetensors"], tmp_path / "m.safetensors")
    assert not (tmp_path / "m.safetensors").exists()


# --------------------------------------------------------------------------------------------- CLI
def _draws(folder: Path, k: int) -> list[Path]:
    g = torch.Generator().manual_seed(3)
    shapes = {"blocks.0.attn.weight": (6, 4), "blocks.0.attn.bias": (6,), "blocks.1.mlp.weight": (3, 6)}
    return [_write(folder, f"gamma_{i}", {n: torch.randn(s, generator=g) for n, s in shapes.items()})
            for i in range(k)]  # fmt: skip


def _edges_into(workspace: Workspace, child: str) -> list[tuple[str, str, dict]]:
    rows = workspace.api.query("SELECT parent, role, attrs FROM edges WHERE child = ?", [child])
    out = [(p, r, json.loads(a) if isinstance(a, str) else a) for p, r, a in rows.values.tolist()]
    return sorted(out, key=lambda e: e[2]["index"])


def test_cli_mean_registers_the_output_with_an_edge_to_every_input(tmp_path, monkeypatch):
    monkeypatch.setattr(vector_ops, "CHUNK_BYTES", 32)  # TIES's threshold passes read the copies too
    home, folder = tmp_path / "home", tmp_path / "user"
    folder.mkdir()
    draws = _draws(folder, 4)
    out = folder / "gamma_bar.safetensors"
    args = [*map(str, draws[:3]), "-o", str(out)]
    result = CliRunner().invoke(app, ["--home", str(home), "vector", "mean", *args])
    assert result.exit_code == 0, (result.output, result.exception)
    workspace = Workspace(str(home))
    record = workspace.api.store.get(Checkpoint(out).sha256())
    printed = result.output.replace("\n", "")  # a long path may be folded
    assert str(out) in printed and record.id in printed
    assert record.kind == "vector" and record.name == "gamma_bar" and record.config["method"] == "mean"
    digests = [Checkpoint(p).sha256() for p in draws]
    assert _edges_into(workspace, record.id) == [(digests[i], "vector", {"index": i}) for i in range(3)]
    kinds = dict(workspace.api.query("SELECT id, kind FROM artifacts").values.tolist())
    assert all(kinds[d] == "vector" for d in digests[:3]) and kinds[record.id] == "vector"
    want = mean(draws[:3], tmp_path / "library.safetensors")
    assert out.read_bytes() == want.read_bytes()  # the same bytes as the library call
    assert workspace.api.store.audit(record.id).status == "ok"

    # Stored vectors by id (a prefix too) and a new path, with TIES; the output is sharded.
    ties_out = folder / "ties"
    args = [digests[0][:12], digests[1], str(draws[3]), "-o", str(ties_out), "--method", "ties"]
    args += ["--density", "0.5"]
    result = CliRunner().invoke(app, ["--home", str(home), "vector", "mean", *args])
    assert result.exit_code == 0, (result.output, result.exception)
    (ties_id,) = workspace.api.query("SELECT id FROM artifacts WHERE name = 'ties'")["id"]
    ties = workspace.api.store.get(ties_id)  # a folder's id is the store's hash of its members
    assert ties.config["method"] == "ties" and ties.config["density"] == 0.5
    assert _edges_into(workspace, ties.id) == [
        (digests[0], "vector", {"index": 0}),
        (digests[1], "vector", {"index": 1}),
        (digests[3], "vector", {"index": 2}),
    ]
    want = _load(mean([draws[0], draws[1], draws[3]], tmp_path / "t.safetensors", method="ties", density=0.5))
    assert all(torch.equal(v, want[k]) for k, v in _load(ties_out).items())
    assert all(workspace.api.store.audit(i).status == "ok" for i in (*digests, record.id, ties.id))


def test_cli_mean_reads_every_input_byte_once(tmp_path, monkeypatch):
    """As `vector extract`: each input read once, hashed and copied into the store from those bytes."""
    folder = tmp_path / "user"
    folder.mkdir()
    draws = _draws(folder, 3)
    read: dict[str, int] = {}
    real_read = vector_ops._read

    def counting_read(path, copy, offset, out):
        read[path.name] = read.get(path.name, 0) + out.size
        return real_read(path, copy, offset, out)

    monkeypatch.setattr(vector_ops, "_read", counting_read)
    workspace = Workspace(str(tmp_path / "home"))
    record = mean_cli(workspace, [str(p) for p in draws], folder / "m.safetensors")
    assert read == {p.name: p.stat().st_size for p in draws}
    for p, edge in zip(draws, _edges_into(workspace, record.id), strict=True):
        stored = workspace.api.store.path(edge[0], verify=False)
        assert edge[0] == Checkpoint(p).sha256() and stored.read_bytes() == p.read_bytes()
        assert os.stat(stored).st_ino != os.stat(p).st_ino  # a copy, never a link to the user's file


def test_cli_mean_refusals_keep_everything_stored(tmp_path):
    """An existing -o, one input, a repeated input, the same bytes twice, a mismatched tensor: exit 2,
    a message naming the problem, nothing registered or written, and what was stored before intact."""
    home, folder = tmp_path / "home", tmp_path / "user"
    folder.mkdir()
    draws = _draws(folder, 3)
    workspace = Workspace(str(home))
    first = mean_cli(workspace, [str(p) for p in draws], folder / "m.safetensors")
    ids = set(workspace.api.store.iter_ids())
    edges = workspace.api.query("SELECT count(*) AS n FROM edges")["n"][0]
    kept = (folder / "m.safetensors").read_bytes()
    bad = _load(draws[0])
    bad["blocks.1.mlp.weight"] = torch.zeros(3, 5)
    bad_path = _write(folder, "reshaped", bad)
    shutil.copy(draws[1], folder / "copy_of_1.safetensors")
    listing = sorted(os.listdir(folder))
    d = [str(p) for p in draws]
    cases = [
        ([d[0], d[1], "-o", str(folder / "m.safetensors")], "already exists"),
        ([d[0], "-o", str(folder / "one.safetensors")], "at least 2 vectors, got 1"),
        ([d[0], d[1], f"{folder}/./gamma_0.safetensors", "-o", str(folder / "r.safetensors")],
         "are the same vector"),
        ([first.id[:12], first.id, "-o", str(folder / "r.safetensors")], "are the same vector"),
        ([d[0], d[0], "-o", str(folder / "r.safetensors")], "is named twice"),
        ([d[0], d[1], str(folder / "copy_of_1.safetensors"), "-o", str(folder / "r.safetensors")],
         "vector 1 and vector 2 are the same bytes"),
        ([d[0], d[1], str(bad_path), "-o", str(folder / "r.safetensors")],
         r"blocks.1.mlp.weight (F32[3, 6] vs F32[3, 5])"),
        ([d[0], d[1], "--method", "ties", "--density", "2", "-o", str(folder / "r.safetensors")],
         "density must be a number in (0, 1]"),
    ]  # fmt: skip
    for args, message in cases:
        proc = run_cli("vector", "mean", *args, home=home, check=False)
        assert proc.returncode == 2, (args, proc.stderr)
        assert message in " ".join(proc.stderr.split()), (message, proc.stderr)
    assert set(workspace.api.store.iter_ids()) == ids
    assert workspace.api.query("SELECT count(*) AS n FROM edges")["n"][0] == edges
    assert all(workspace.api.store.audit(i).status == "ok" for i in ids)
    assert (folder / "m.safetensors").read_bytes() == kept and sorted(os.listdir(folder)) == listing
    assert os.listdir(workspace.api.store._p("tmp")) == []


def test_cli_mean_does_not_import_torch(tmp_path):
    import subprocess
    import sys

    folder = tmp_path / "user"
    folder.mkdir()
    draws = [str(p) for p in _draws(folder, 3)]
    code = f"""
import sys
from pathlib import Path
from capvector.tasks.vector_commands import mean_cli
from capvector.tasks.runtime.workspace import Workspace
ws = Workspace({str(tmp_path / "home")!r})
mean_cli(ws, {draws!r}, Path({str(folder / "m.safetensors")!r}))
mean_cli(ws, {draws!r}, Path({str(folder / "t.safetensors")!r}), "ties", 0.5)
print("torch" in sys.modules)
"""
    repo = Path(__file__).resolve().parent.parent
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=repo)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "False"
