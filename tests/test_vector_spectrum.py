"""`capvector vector spectrum`: energy ranks of known spectra, module kinds of a real policy's tensors,
and the command's artifact (edges to its inputs, reused when called again, rows in the catalogue that a
rebuild restores)."""

import json

import duckdb
import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file
from typer.testing import CliRunner

from capvector.artifacts.api import ArtifactsAPI
from capvector.artifacts.catalogue import Catalogue
from capvector.artifacts.schema import MIGRATIONS
from capvector.core.policies.base import build_policy, save_policy
from capvector.core.vectors.spectrum import energy_rank, module_kind, spectrum, tensor_spectrum
from capvector.core.vectors.vector_ops import VectorOpError
from capvector.flows.cli.main import app

POLICY = {"d_model": 16, "n_layers": 1, "n_heads": 2, "chunk_size": 2}


def _with_spectrum(s: list[float], rows: int, cols: int, seed: int = 0) -> np.ndarray:
    """U·diag(s)·Vᵀ with random orthonormal U (rows × k) and V (cols × k): singular values s."""
    rng = np.random.default_rng(seed)
    u = np.linalg.qr(rng.standard_normal((rows, len(s))))[0]
    v = np.linalg.qr(rng.standard_normal((cols, len(s))))[0]
    return u @ np.diag(s) @ v.T


# Energies (squared values) and the smallest k with cumulative energy ≥ 50 / 90 / 99 %, by hand:
# rank 1: all of it in one value; flat (10 equal): k/10, exactly 5 and 9 at 50 and 90 % (ties);
# geometric (0.5^i, i < 10): energy 0.25^i, cumulative (1 − 0.25^k) / (1 − 0.25^10):
# k=1 0.750, k=2 0.938, k=3 0.984, k=4 0.996.
KNOWN = [
    ("rank one", [3.0] + [0.0] * 5, (1, 1, 1)),
    ("flat", [0.1] * 10, (5, 9, 10)),  # cumulative sums of 0.1² fall a hair short of the ties
    ("geometric", [0.5**i for i in range(10)], (1, 2, 4)),
]


@pytest.mark.parametrize(("name", "values", "ranks"), KNOWN, ids=[k[0] for k in KNOWN])
def test_ranks_of_matrices_of_known_spectrum(name, values, ranks):
    row = tensor_spectrum("w", _with_spectrum(values, 12, 10))
    assert (row.rank50, row.rank90, row.rank99) == ranks
    assert row.full_rank == 10 and (row.rows, row.cols) == (12, 10)
    assert row.top == pytest.approx(max(values)) and len(row.singular_values) == 10
    assert [energy_rank(np.array(values), f) for f in (0.5, 0.9, 0.99)] == list(ranks)


def test_an_update_of_zeros_holds_no_energy():
    row = tensor_spectrum("w", np.zeros((4, 3)))
    assert (row.rank50, row.rank90, row.rank99, row.top, row.full_rank) == (0, 0, 0, 0.0, 3)


@pytest.fixture(scope="module")
def policies(tmp_path_factory):
    """Two tiny flow policies (backbone, state encoder, action expert and head): A and B."""
    folder = tmp_path_factory.mktemp("policies")
    paths = {}
    for seed, name in enumerate("AB"):
        torch.manual_seed(seed)
        paths[name] = save_policy(
            build_policy({"type": "flow", **POLICY}, "cpu"), folder / f"{name}.safetensors"
        )
    return paths


def test_module_kinds_of_a_real_policy_checkpoint(policies):
    rows = spectrum(policies["B"], policies["A"])
    a, b = load_file(str(policies["A"])), load_file(str(policies["B"]))
    assert [r.tensor for r in rows] == [n for n, t in b.items() if t.dim() == 2]
    kinds = {r.tensor: r.kind for r in rows}
    for name, kind in kinds.items():
        if ".attn." in name:
            assert kind == "attention", name
        elif ".mlp." in name:
            assert kind == "mlp", name
        elif name.split(".")[0] in ("state", "proprio"):
            assert kind == "encoder", name
        elif name.startswith(("action_head.", "action_expert.action_in.", "action_expert.time_mlp_")):
            assert kind == "action_head", name
        else:
            assert kind == "other", name
    assert {"attention", "mlp", "encoder", "action_head", "other"} == set(kinds.values())
    assert kinds["action_expert.layers.0.attn.q_proj.weight"] == "attention"
    assert kinds["language.embed.weight"] == "other" and kinds["action_expert.position"] == "other"
    assert module_kind("vision.proj.weight") == "encoder"  # pixels mode
    name = "backbone.layers.0.mlp.fc1.weight"
    expected = torch.linalg.svdvals((b[name] - a[name]).double()).numpy()
    (row,) = [r for r in rows if r.tensor == name]
    np.testing.assert_allclose(row.singular_values, expected, rtol=1e-10)


def test_a_subtrahend_without_a_tensor_or_with_nan_is_refused(policies, tmp_path):
    b = load_file(str(policies["B"]))
    name = "backbone.layers.0.mlp.fc1.weight"
    save_file({n: t for n, t in b.items() if n != name}, str(tmp_path / "short.safetensors"))
    with pytest.raises(VectorOpError, match="1 tensor.*missing"):
        spectrum(policies["B"], tmp_path / "short.safetensors")
    b[name][0, 0] = float("nan")
    save_file(b, str(tmp_path / "nan.safetensors"))
    with pytest.raises(VectorOpError, match=name.replace(".", r"\.")):
        spectrum(tmp_path / "nan.safetensors", policies["A"])


def _cli(home, *args: str):
    result = CliRunner().invoke(app, ["--home", str(home), *args])
    assert result.exit_code == 0, (result.output, result.exception)
    return result


def _spectrum_rows(api: ArtifactsAPI, spectrum_id: str) -> list[tuple]:
    return api.query(
        "SELECT tensor, module_kind, rows, cols, full_rank, rank50, rank90, rank99, top_singular_value "
        "FROM vector_spectrum WHERE spectrum_id = ? ORDER BY tensor",
        [spectrum_id],
    ).values.tolist()


def test_the_command_registers_one_artifact_reuses_it_and_the_catalogue_rebuilds_it(policies, tmp_path):
    home, a, b = tmp_path / "home", str(policies["A"]), str(policies["B"])
    figure = tmp_path / "spectrum.png"
    first = _cli(home, "vector", "spectrum", a, b, "--json", "--figure", str(figure))
    rows = json.loads(first.stdout)
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    api = ArtifactsAPI(str(home))
    (spectrum_id,) = api.query("SELECT id FROM artifacts WHERE kind = 'vector_spectrum'")["id"].tolist()
    assert f"{spectrum_id} (recorded)" in first.stderr
    edges = api.query(
        "SELECT p.name, e.role, p.kind FROM edges e JOIN artifacts p ON p.id = e.parent WHERE e.child = ?",
        [spectrum_id],
    ).values.tolist()
    assert sorted(edges) == [
        ["A.safetensors", "subtrahend", "checkpoint"],
        ["B.safetensors", "spectrum_of", "checkpoint"],
    ]

    before = set(api.store.iter_ids())
    again = _cli(home, "vector", "spectrum", a, b)
    assert f"{spectrum_id} (recorded before: reused)" in again.stderr
    assert set(ArtifactsAPI(str(home)).store.iter_ids()) == before

    table = _spectrum_rows(api, spectrum_id)
    expected = [
        [
            r["tensor"],
            r["kind"],
            r["rows"],
            r["cols"],
            r["full_rank"],
            r["rank50"],
            r["rank90"],
            r["rank99"],
            r["top"],
        ]
        for r in sorted(rows, key=lambda r: r["tensor"])
    ]
    assert table == expected

    con = duckdb.connect(str(api.catalogue.path))
    con.execute("DELETE FROM vector_spectrum")
    con.close()
    assert _spectrum_rows(ArtifactsAPI(str(home)), spectrum_id) == []
    _cli(home, "catalogue", "rebuild")
    assert _spectrum_rows(ArtifactsAPI(str(home)), spectrum_id) == expected


def test_the_spectrum_of_a_vector_has_one_parent(policies, tmp_path):
    home = tmp_path / "home"
    gamma = tmp_path / "gamma.safetensors"
    _cli(home, "vector", "extract", str(policies["B"]), str(policies["A"]), "-o", str(gamma))
    _cli(home, "vector", "spectrum", str(gamma))
    api = ArtifactsAPI(str(home))
    (spectrum_id,) = api.query("SELECT id FROM artifacts WHERE kind = 'vector_spectrum'")["id"].tolist()
    parents = api.query(
        "SELECT p.kind, e.role FROM edges e JOIN artifacts p ON p.id = e.parent WHERE e.child = ?",
        [spectrum_id],
    ).values.tolist()
    assert parents == [["vector", "spectrum_of"]]
    assert api.query("SELECT DISTINCT subtrahend_id FROM vector_spectrum")["subtrahend_id"].isna().all()


def test_an_older_catalogue_gains_the_spectrum_table(tmp_path):
    path = tmp_path / "c.duckdb"
    Catalogue(path, migrations=[m for m in MIGRATIONS if m[0] <= 3])
    catalogue = Catalogue(path)
    assert catalogue.schema_version() == MIGRATIONS[-1][0] >= 4
    assert "top_singular_value" in catalogue.query("DESCRIBE vector_spectrum")["column_name"].tolist()
