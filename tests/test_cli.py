"""The `capvector` CLI: vector arithmetic against torch, catalogue registration and lineage, the
catalogue commands, and the clear errors (exit 2, nothing written) for bad input.

Error paths go through the real console entry point (`run_cli`, a subprocess): its exit codes and
messages are what a user sees. Read-only happy paths use typer's CliRunner on the same app.
"""

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from conftest import REPO, own_server_env, run_cli
from safetensors.torch import load_file, save_file
from typer.testing import CliRunner

from capvector.artifacts.api import ArtifactsAPI
from capvector.artifacts.scores import read_scores
from capvector.core.vectors.safetensors_io import Checkpoint
from capvector.flows.cli.main import app

SHAPES = {"blocks.0.attn.weight": (6, 4), "blocks.0.attn.bias": (6,), "blocks.1.mlp.weight": (3, 6)}


def _random_checkpoint(seed: int, scale: float = 1.0, base: dict | None = None) -> dict:
    gen = torch.Generator().manual_seed(seed)
    return {
        k: (base[k] if base else 0) + scale * torch.randn(shape, generator=gen) for k, shape in SHAPES.items()
    }


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory) -> dict:
    """θ_pt, θ_ft, θ_ao as small random single-file checkpoints, plus two that do not match them."""
    root = tmp_path_factory.mktemp("ckpts")
    pt = _random_checkpoint(0)
    ft = _random_checkpoint(1, 0.1, pt)
    ao = _random_checkpoint(2, 0.1, ft)
    missing = {k: v for k, v in ao.items() if k != "blocks.1.mlp.weight"}
    reshaped = {**ao, "blocks.0.attn.bias": torch.randn(7)}
    paths = {}
    for name, tensors in [("pt", pt), ("ft", ft), ("ao", ao), ("missing", missing), ("reshaped", reshaped)]:
        paths[name] = root / f"{name}.safetensors"
        save_file(tensors, str(paths[name]))
    return {"paths": paths, "pt": pt, "ft": ft, "ao": ao}


def _edges_into(api: ArtifactsAPI, child_name: str) -> dict[str, list[tuple[str, dict | None]]]:
    """{parent name: [(role, attrs)]} for the edges into the artifact called `child_name`."""
    frame = api.query(
        "SELECT p.name AS parent, e.role, e.attrs FROM edges e "
        "JOIN artifacts p ON p.id = e.parent JOIN artifacts c ON c.id = e.child WHERE c.name = ?",
        [child_name],
    )
    out: dict[str, list] = {}
    for r in frame.itertuples():
        attrs = json.loads(r.attrs) if isinstance(r.attrs, str) else r.attrs
        out.setdefault(r.parent, []).append((r.role, attrs))
    return out


def _kind_count(home, kind: str) -> int:
    return int(
        ArtifactsAPI(str(home)).query("SELECT count(*) AS n FROM artifacts WHERE kind = ?", [kind])["n"][0]
    )


def invoke(home, *args: str):
    result = CliRunner().invoke(app, ["--home", str(home), *args])
    assert result.exit_code == 0, (result.output, result.exception)
    return result


# ---------------------------------------------------------------------------- vector arithmetic
def test_extract_merge_stats_match_torch_and_register_lineage(ckpts, tmp_path):
    home, p = tmp_path / "home", ckpts["paths"]
    gamma, delta, merged = tmp_path / "gamma.safetensors", tmp_path / "delta.safetensors", tmp_path / "merged"

    run_cli(
        "vector", "extract", str(p["ao"]), str(p["ft"]), "-o", str(gamma), "--base", str(p["pt"]), home=home
    )
    run_cli("vector", "extract", str(p["ft"]), str(p["pt"]), "-o", str(delta), home=home)
    got = load_file(str(gamma))
    assert set(got) == set(SHAPES)
    for k in SHAPES:
        torch.testing.assert_close(got[k], ckpts["ao"][k] - ckpts["ft"][k], rtol=0, atol=0)

    run_cli(
        "vector", "merge", str(p["pt"]),
        "--vector", str(gamma), "--alpha", "1.1", "--vector", str(delta), "--alpha", "-0.5",
        "-o", str(merged), home=home,
    )  # fmt: skip
    assert merged.is_dir() and list(merged.glob("*.safetensors")), merged  # a sharded directory
    out = Checkpoint(merged)
    assert sorted(out.keys()) == sorted(SHAPES)
    for k in SHAPES:
        g, d = ckpts["ao"][k] - ckpts["ft"][k], ckpts["ft"][k] - ckpts["pt"][k]
        expected = ckpts["pt"][k].double() + 1.1 * g.double() - 0.5 * d.double()
        torch.testing.assert_close(out.get(k).double(), expected, rtol=1e-6, atol=1e-6)
        assert out.get(k).dtype == torch.float32

    proc = run_cli("vector", "stats", str(gamma), "--base", str(p["pt"]), "--json", home=home)
    rows = json.loads(proc.stdout)
    tensors = {r["name"]: r for r in rows if r["level"] == "tensor"}
    assert set(tensors) == set(SHAPES)
    total_sq = total_base_sq = 0.0
    for k in SHAPES:
        g = (ckpts["ao"][k] - ckpts["ft"][k]).double()
        assert tensors[k]["numel"] == g.numel()
        assert tensors[k]["l2"] == pytest.approx(float(g.norm()), rel=1e-9)
        base_norm = float(ckpts["pt"][k].double().norm())
        assert tensors[k]["relative_norm"] == pytest.approx(float(g.norm()) / base_norm, rel=1e-9)
        total_sq += float((g * g).sum())
        total_base_sq += base_norm**2
    (overall,) = [r for r in rows if r["level"] == "all"]
    assert overall["numel"] == sum(torch.Size(s).numel() for s in SHAPES.values())
    assert overall["l2"] == pytest.approx(total_sq**0.5, rel=1e-9)
    assert overall["relative_norm"] == pytest.approx((total_sq / total_base_sq) ** 0.5, rel=1e-9)
    groups = {r["name"] for r in rows if r["level"] == "group"}
    assert groups == {"blocks.0", "blocks.1"}

    # Inputs imported, outputs registered, one edge per input with its role (and α on vector edges).
    api = ArtifactsAPI(str(home))
    kinds = dict(api.query("SELECT name, kind FROM artifacts").values.tolist())
    assert kinds["gamma"] == "vector" and kinds["delta"] == "vector" and kinds["merged"] == "checkpoint"
    for name in ("pt.safetensors", "ft.safetensors", "ao.safetensors"):
        assert kinds[name] == "checkpoint", kinds
    assert {k: [r for r, _ in v] for k, v in _edges_into(api, "gamma").items()} == {
        "ao.safetensors": ["minuend"],
        "ft.safetensors": ["subtrahend"],
        "pt.safetensors": ["base"],
    }
    merge_edges = _edges_into(api, "merged")
    assert [r for r, _ in merge_edges["pt.safetensors"]] == ["base"]
    assert [(r, a["alpha"]) for r, a in merge_edges["gamma"]] == [("vector", 1.1)]
    assert [(r, a["alpha"]) for r, a in merge_edges["delta"]] == [("vector", -0.5)]
    merged_id = api.query("SELECT id FROM artifacts WHERE name = 'merged'")["id"][0]
    assert sorted((v.vector_name, v.alpha) for v in api.vectors_merged_into(merged_id)) == [
        ("delta", -0.5),
        ("gamma", 1.1),
    ]
    gamma_id = api.query("SELECT id FROM artifacts WHERE name = 'gamma'")["id"][0]
    stats = api.query("SELECT tensor, l2 FROM vector_stats WHERE vector_id = ?", [gamma_id])
    l2 = dict(stats.values.tolist())
    assert l2["blocks.1.mlp.weight"] == pytest.approx(tensors["blocks.1.mlp.weight"]["l2"])

    # A cosine against a reference vector traces to that vector and to the base of the norms.
    run_cli("vector", "stats", str(gamma), "--base", str(p["pt"]), "--reference", str(delta), home=home)
    with_ref = api.query(
        "SELECT a.id FROM artifacts a JOIN edges e ON e.child = a.id AND e.role = 'reference' "
        "WHERE a.kind = 'vector_stats'"
    )["id"]
    assert len(with_ref) == 1
    parents = api.query(
        "SELECT p.name, e.role FROM edges e JOIN artifacts p ON p.id = e.parent WHERE e.child = ?",
        [with_ref[0]],
    )
    assert sorted(parents.values.tolist()) == [
        ["delta", "reference"],
        ["gamma", "stats_of"],
        ["pt.safetensors", "base"],
    ]

    # The same operations by artifact id give the same bytes.
    again = tmp_path / "again.safetensors"
    ao_id = api.query("SELECT id FROM artifacts WHERE name = 'ao.safetensors'")["id"][0]
    ft_id = api.query("SELECT id FROM artifacts WHERE name = 'ft.safetensors'")["id"][0]
    invoke(home, "vector", "extract", ao_id[:12], ft_id, "-o", str(again))
    for k, v in load_file(str(again)).items():
        assert torch.equal(v, got[k]), k


@pytest.mark.parametrize(
    ("bad", "tensor"), [("missing", "blocks.1.mlp.weight"), ("reshaped", "blocks.0.attn.bias")]
)
def test_extract_of_mismatched_checkpoints_exits_2_naming_the_tensor(ckpts, tmp_path, bad, tensor):
    home, out = tmp_path / "home", tmp_path / "gamma.safetensors"
    proc = run_cli("vector", "extract", str(ckpts["paths"][bad]), str(ckpts["paths"]["ft"]), "-o", str(out),
                   home=home, check=False)  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert tensor in proc.stderr and "Traceback" not in proc.stderr
    assert not out.exists() and not list(tmp_path.glob("gamma*"))
    assert _kind_count(home, "vector") == 0


def test_merge_with_mismatched_vector_exits_2_and_writes_nothing(ckpts, tmp_path):
    home, out = tmp_path / "home", tmp_path / "merged"
    proc = run_cli("vector", "merge", str(ckpts["paths"]["pt"]), "--vector", str(ckpts["paths"]["reshaped"]),
                   "--alpha", "1.0", "-o", str(out), home=home, check=False)  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert "blocks.0.attn.bias" in proc.stderr
    assert not out.exists() and [x.name for x in tmp_path.iterdir()] == ["home"]
    frame = ArtifactsAPI(str(home)).query("SELECT count(*) AS n FROM artifacts WHERE name = 'merged'")
    assert frame["n"][0] == 0


def test_merge_needs_one_alpha_per_vector(ckpts, tmp_path):
    home, out, p = tmp_path / "home", tmp_path / "merged", ckpts["paths"]
    proc = run_cli("vector", "merge", str(p["pt"]), "--vector", str(p["ft"]), "--vector", str(p["ao"]),
                   "--alpha", "1.1", "-o", str(out), home=home, check=False)  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert "2 --vector but 1 --alpha" in proc.stderr and "Traceback" not in proc.stderr
    assert not out.exists()


def test_existing_output_is_refused(ckpts, tmp_path):
    home, out, p = tmp_path / "home", tmp_path / "gamma.safetensors", ckpts["paths"]
    out.write_bytes(b"keep me")
    proc = run_cli("vector", "extract", str(p["ao"]), str(p["ft"]), "-o", str(out), home=home, check=False)
    assert proc.returncode == 2, proc.stderr
    assert "already exists" in proc.stderr and "Traceback" not in proc.stderr
    assert out.read_bytes() == b"keep me"


# ---------------------------------------------------------------------------- catalogue commands
def test_import_list_show_and_sql(ckpts, tmp_path):
    home = tmp_path / "home"
    proc = run_cli("import", str(ckpts["paths"]["pt"]), "--name", "outside-pt", home=home)
    (artifact_id,) = re.findall(r"\b[0-9a-f]{64}\b", proc.stdout)

    listed = json.loads(invoke(home, "artifacts", "list", "--json").stdout)
    assert [(r["id"], r["kind"], r["name"]) for r in listed] == [(artifact_id, "checkpoint", "outside-pt")]
    assert listed[0]["size_bytes"] == ckpts["paths"]["pt"].stat().st_size

    shown = json.loads(invoke(home, "artifacts", "show", artifact_id[:10]).stdout)
    assert shown["id"] == artifact_id and shown["kind"] == "checkpoint"
    assert shown["config"]["imported_from"] == str(ckpts["paths"]["pt"].resolve())
    stored = ArtifactsAPI(str(home)).path(artifact_id)
    assert load_file(str(stored)).keys() == ckpts["pt"].keys()

    got = invoke(home, "artifacts", "get", artifact_id[:10], "-o", str(tmp_path / "out")).stdout.strip()
    assert Path(got) == tmp_path / "out" and Path(got).read_bytes() == ckpts["paths"]["pt"].read_bytes()
    into = tmp_path / "folder"
    into.mkdir()
    got = invoke(home, "artifacts", "get", artifact_id, "-o", str(into)).stdout.strip()
    assert Path(got) == into / stored.name and Path(got).read_bytes() == stored.read_bytes()
    again = run_cli("artifacts", "get", artifact_id, "-o", str(tmp_path / "out"), home=home, check=False)
    assert again.returncode == 2 and "exists" in again.stderr, again.stderr

    rows = json.loads(
        invoke(home, "sql", "SELECT kind, count(*) AS n FROM artifacts GROUP BY kind", "--json").stdout
    )
    assert rows == [{"kind": "checkpoint", "n": 1}]
    refused = run_cli("sql", "DELETE FROM artifacts", home=home, check=False)
    assert refused.returncode == 2 and "only reading statements" in refused.stderr, refused.stderr
    assert _kind_count(home, "checkpoint") == 1


def test_import_of_a_truncated_file_exits_2_and_registers_nothing(ckpts, tmp_path):
    home, broken = tmp_path / "home", tmp_path / "broken.safetensors"
    broken.write_bytes(ckpts["paths"]["pt"].read_bytes()[:-10])
    proc = run_cli("import", str(broken), home=home, check=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert _kind_count(home, "checkpoint") == 0


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (("artifacts", "show", "0123456789abcdef"), "0123456789abcdef"),
        (("artifacts", "show", "not-an-id!"), "not-an-id!"),
        (("lineage", "abcdef012345"), "abcdef012345"),
        (("scores", "XYZ"), "XYZ"),
        (
            ("evaluate", "abcdef012345", "--tasks", "reach-v3", "--obs-mode", "pixels", "--camera", "cornr3"),
            "cornr3",
        ),
    ],
)
def test_unknown_or_malformed_artifact_id_is_a_clear_error(tmp_path, args, needle):
    proc = run_cli(*args, home=tmp_path / "home", check=False)
    assert proc.returncode == 2, proc.stderr
    assert needle in proc.stderr and "error" in proc.stderr and "Traceback" not in proc.stderr


# ---------------------------------------------------------------------------- config and schedule
def test_unknown_override_key_is_named(tmp_path):
    proc = run_cli(
        "run", "--preset", "smoke", "--set", "pretrain.stepz=3", home=tmp_path / "home", check=False
    )
    assert proc.returncode == 2, proc.stderr
    assert "pretrain.stepz" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "home").exists() or _kind_count(tmp_path / "home", "dataset") == 0


def test_schedule_check_validates_the_cron(tmp_path):
    bad = run_cli("schedule", "--cron", "not a cron", "--check", home=tmp_path, check=False)
    assert bad.returncode == 2 and "invalid cron expression 'not a cron'" in bad.stderr, bad.stderr
    good = run_cli("schedule", "--cron", "0 3 * * *", "--check", home=tmp_path)
    assert "scheduled-reevaluation" in good.stdout and "0 3 * * *" in good.stdout


# ---------------------------------------------------------------------------- on the smoke run
def test_lineage_formats_and_descendants(smoke_home):
    home, ids = smoke_home
    capvector = ids["checkpoints"]["capvector/seed0"]
    rows = json.loads(invoke(home, "lineage", capvector[:12], "--format", "json").stdout)
    by_id = {r["id"]: r for r in rows}
    assert capvector not in by_id  # ancestors only
    assert (by_id[ids["meta"]]["depth"], by_id[ids["meta"]]["roles"]) == (1, ["init"])
    assert by_id[ids["vector"]]["depth"] == 1 and by_id[ids["pretrained"]]["depth"] == 2
    assert (
        by_id[ids["auxiliary"]]["roles"][-1] == "minuend"
        and by_id[ids["standard"]]["roles"][-1] == "subtrahend"
    )
    assert {ids["datasets"][k] for k in ("pretrain", "extraction", "downstream")} <= set(by_id)

    mermaid = invoke(home, "lineage", capvector, "--format", "mermaid").stdout
    assert mermaid.startswith("graph BT")
    assert re.search(rf'n{ids["meta"][:12]}\[[^\]]*\]"\] -->\|init\| n{capvector[:12]}', mermaid), mermaid
    assert f"n{ids['vector'][:12]}" in mermaid

    tree = invoke(home, "lineage", capvector).stdout
    assert tree.splitlines()[0].endswith(f"[{capvector[:12]}]")
    assert "(init) checkpoint" in tree and ids["meta"][:12] in tree and ids["vector"][:12] in tree

    down = json.loads(invoke(home, "lineage", ids["vector"], "--descendants", "--format", "json").stdout)
    down_ids = {r["id"] for r in down}
    assert {ids["meta"], capvector} <= down_ids
    assert ids["checkpoints"]["sft/seed0"] not in down_ids  # θ_pt + SFT never saw γ
    assert invoke(home, "lineage", ids["vector"], "--descendants", "--format", "mermaid").stdout.startswith(
        "graph TD"
    )


def test_scores_compare_and_report(smoke_home, tmp_path):
    home, ids = smoke_home
    api = ArtifactsAPI(str(home))
    capvector, sft = ids["checkpoints"]["capvector/seed0"], ids["checkpoints"]["sft/seed0"]
    evaluation = api.get(ids["evaluations"]["capvector/seed0"])
    (scores,) = read_scores(api, evaluations=[evaluation.id])
    protocol = scores.fingerprint  # other tests add other protocols

    rows = json.loads(invoke(home, "scores", capvector, "--fingerprint", protocol, "--json").stdout)
    mine = [r for r in rows if r["evaluation_id"] == evaluation.id]
    assert [(r["checkpoint_id"], r["task"], r["n_episodes"], r["depth"]) for r in mine] == [
        (capvector, "button-press-topdown-v3", 2, 0)
    ]
    assert mine[0]["success_rate"] == scores.success_rates["button-press-topdown-v3"]
    fingerprint = mine[0]["fingerprint"]

    png = tmp_path / "x.png"
    result = json.loads(
        invoke(
            home, "compare", capvector, sft, "--fingerprint", fingerprint, "--plot", str(png), "--json"
        ).stdout
    )
    assert [r["checkpoint_id"] for r in result["rows"]] == [capvector, sft]
    assert result["fingerprint"] == fingerprint
    assert result["rows"][0]["success_rates"] == scores.success_rates
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    out = tmp_path / "tmp" / "results.md"
    invoke(home, "report", ids["report"], "-o", str(out))
    text = out.read_text()
    assert text.startswith("# Study `smoke`") and ids["report"][:12] in text  # a run's report is a study's
    figures = re.findall(r"!\[[^\]]*\]\(([^)]+\.png)\)", text)
    assert {"results_curves.png", "results_forest.png", "results_tasks.png"} <= set(figures), figures
    for name in figures:
        assert (out.parent / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    for arm in ("| SFT |", "| auxiliary SFT |", "| CapVector |"):
        assert arm in text, arm


def _session_alive(sid: int) -> list[int]:
    alive = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] != "Z":  # fields[3] is the session id
            alive.append(int(stat.parent.name))
    return alive


def _children_of(pid: int) -> dict[int, str]:
    children = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, IndexError):
            if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == pid:
                cmdline = (stat.parent / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
                children[int(stat.parent.name)] = cmdline
    return children


def test_sigterm_stops_the_embedded_prefect_server_and_workers(tmp_path):
    env = own_server_env({**os.environ, "CAPVECTOR_HOME": str(tmp_path / "home"), "CAPVECTOR_QUIET": "1"})
    proc = subprocess.Popen(
        [sys.executable, "-m", "capvector", "run", "--preset", "smoke"],
        cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while len(_session_alive(proc.pid)) < 3 and time.monotonic() < deadline:  # CLI, workers, tracker
            time.sleep(0.2)
        assert proc.poll() is None and len(_session_alive(proc.pid)) >= 3, "helpers never started"
        # the server runs in a session of its own (out of reach of the terminal's Ctrl-C)
        servers = [p for p, cmd in _children_of(proc.pid).items() if "uvicorn" in cmd]
        assert servers, "the run's Prefect server never started"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 128 + signal.SIGTERM
        deadline = time.monotonic() + 30
        while (_session_alive(proc.pid) or _session_alive(servers[0])) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert _session_alive(proc.pid) == [], "processes outlived the terminated CLI"
        assert _session_alive(servers[0]) == [], "the Prefect server outlived the terminated CLI"
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)


# A handler that raises (as Prefect's does inside a flow run) and a library that swallows the
# exception (as DuckDB does: "Query interrupted"): the signal must still stop the helpers, exit 143.
SWALLOWED_SIGTERM = """
import os, signal, subprocess, sys
import capvector.flows.cli.main as cli

def app(prog_name, standalone_mode):
    helper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])
    print(helper.pid, flush=True)
    def raising_handler(signum, frame):
        raise InterruptedError("termination signal")
    signal.signal(signal.SIGTERM, raising_handler)
    try:
        os.kill(os.getpid(), signal.SIGTERM)
    except InterruptedError:
        raise RuntimeError("Query interrupted") from None

cli.app = app
cli.main()
"""


def test_sigterm_swallowed_by_a_library_still_stops_helpers_and_exits_143():
    proc = subprocess.run(
        [sys.executable, "-c", SWALLOWED_SIGTERM], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 128 + signal.SIGTERM, proc.stderr
    helper = int(proc.stdout.split()[0])
    deadline = time.monotonic() + 10
    while Path(f"/proc/{helper}").exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    stat = Path(f"/proc/{helper}/stat")
    assert not stat.exists() or stat.read_text().rsplit(")", 1)[1].split()[0] == "Z", (
        "helper outlived the CLI"
    )


@pytest.mark.parametrize("policy_type", ["l1_chunk", "flow"])
def test_a_policy_merged_on_the_cli_is_a_loadable_policy(tmp_path, policy_type):
    """`vector merge` keeps the base's policy config: its output evaluates like any checkpoint."""
    from capvector.core.policies.base import build_policy, save_policy
    from capvector.tasks.runtime.workspace import Workspace
    from capvector.tasks.trained_policy import load_trained_policy

    home = tmp_path / "home"
    spec = {"type": policy_type, "d_model": 16, "n_layers": 1, "n_heads": 2, "chunk_size": 2}
    paths = {}
    for seed, name in enumerate(["pt", "ft", "ao"]):
        torch.manual_seed(seed)
        paths[name] = save_policy(build_policy(spec, "cpu"), tmp_path / f"{name}.safetensors")
    gamma, merged = tmp_path / "gamma.safetensors", tmp_path / "merged.safetensors"
    invoke(home, "vector", "extract", str(paths["ao"]), str(paths["ft"]), "-o", str(gamma))
    out = invoke(
        home, "vector", "merge", str(paths["pt"]), "--vector", str(gamma), "--alpha", "1.1", "-o", str(merged)
    )
    merged_id = out.stdout.split("(artifact ")[1].split(")")[0]
    policy, form = load_trained_policy(Workspace(str(home)), merged_id, device="cpu")
    assert policy.type_name == policy_type and form.form == "dense"
    expected = {
        k: v + 1.1 * (load_file(str(paths["ao"]))[k] - load_file(str(paths["ft"]))[k])
        for k, v in load_file(str(paths["pt"])).items()
        if v.is_floating_point()
    }
    for k, v in expected.items():
        torch.testing.assert_close(policy.state_dict()[k], v)


def _main_with_command(monkeypatch, failing) -> SystemExit:
    """Run `capvector.flows.cli.main.main` on a command registered just for the test; the SystemExit it ends
    with."""
    from capvector.flows.cli import main as cli

    cli.app.command("failing-for-test")(failing)
    try:
        monkeypatch.setattr(sys, "argv", ["capvector", "failing-for-test"])
        with pytest.raises(SystemExit) as exit_info:
            cli.main()
        return exit_info.value
    finally:
        cli.app.registered_commands.pop()


def test_an_exit_code_from_a_command_reaches_the_shell(monkeypatch):
    """click returns a typer.Exit's code under standalone_mode=False; main() must not drop it."""
    import typer

    def failing() -> None:
        raise typer.Exit(3)

    assert _main_with_command(monkeypatch, failing).code == 3


def test_an_error_naming_rich_markup_prints_it_verbatim(monkeypatch, capsys):
    def failing() -> None:
        raise ValueError("tensor 'x[/bold]' is bad")

    assert _main_with_command(monkeypatch, failing).code == 2
    assert "tensor 'x[/bold]' is bad" in capsys.readouterr().err


def test_on_a_smoke_run_every_edge_appears_in_the_lineage_views(smoke_home):
    """History is a DAG: the mermaid view of the report's ancestors draws every edge among them."""
    home, ids = smoke_home
    api = ArtifactsAPI(str(home))
    report = ids["report"]
    ancestors = {r["id"] for r in json.loads(invoke(home, "lineage", report, "--format", "json").stdout)}
    ancestors.add(report)
    edges = {
        (parent[:12], role, child[:12])
        for parent, child, role in api.query("SELECT parent, child, role FROM edges").values.tolist()
        if parent in ancestors and child in ancestors
    }
    assert len(edges) > 17  # data, init, minuend/subtrahend, base, vector, evaluations, report inputs
    mermaid = invoke(home, "lineage", report, "--format", "mermaid").stdout
    drawn = {  # an edge's label is its role, a merge's vector edge with its α ("vector α=1.1")
        (parent, label.split(" α=")[0], child)
        for parent, label, child in re.findall(
            r'n([0-9a-f]{12})\["[^"]*"\] -->\|([^|]+)\| n([0-9a-f]{12})\[', mermaid
        )
    }
    assert edges <= drawn, sorted(edges - drawn)
    tree = invoke(home, "lineage", report).stdout
    for parent, _, child in edges:
        assert parent in tree and child in tree


def test_every_read_command_prints_json_with_json(smoke_home, ckpts, tmp_path):
    """Issue 37: a script can pass `--json` to every read command and parse what it prints; where a
    command has `--format json`, `--json` prints the same."""
    home, ids = smoke_home
    api = ArtifactsAPI(str(home))
    capvector, sft = ids["checkpoints"]["capvector/seed0"], ids["checkpoints"]["sft/seed0"]
    (scored,) = read_scores(api, evaluations=[ids["evaluations"]["capvector/seed0"]])
    protocol = ["--fingerprint", scored.fingerprint[:12]]  # other tests add other protocols
    commands = {
        "artifacts list": ["artifacts", "list"],
        "artifacts show": ["artifacts", "show", capvector[:12]],
        "lineage": ["lineage", capvector],
        "scores": ["scores", capvector, *protocol],
        "compare": ["compare", capvector, sft, *protocol],
        "report": ["report", ids["report"], "-o", str(tmp_path / "report.md")],
        "sql": ["sql", "SELECT kind, count(*) AS n FROM artifacts GROUP BY kind"],
        "runs": ["runs", *protocol],
        "export": ["export", str(tmp_path / "export"), *protocol],
        "verify": ["verify", capvector],
        "catalogue verify": ["catalogue", "verify"],
    }
    got = {name: json.loads(invoke(home, *args, "--json").stdout) for name, args in commands.items()}
    got["config show"] = json.loads(invoke(home, "config", "show", "--preset", "smoke", "--json").stdout)
    vector = ["vector", "stats", str(ckpts["paths"]["ao"]), "--base", str(ckpts["paths"]["pt"]), "--json"]
    got["vector stats"] = json.loads(invoke(tmp_path / "home", *vector).stdout)
    assert got["artifacts show"]["id"] == capvector and capvector in {r["id"] for r in got["artifacts list"]}
    for name, args in (("lineage", ["lineage", capvector]), ("runs", ["runs", *protocol])):
        assert got[name] == json.loads(invoke(home, *args, "--format", "json").stdout), name
    assert {r["checkpoint_id"] for r in got["scores"]} >= {capvector}
    assert [r["checkpoint_id"] for r in got["compare"]["rows"]] == [capvector, sft]
    assert got["report"] == {"path": str(tmp_path / "report.md"), "kind": "study", "id": ids["report"]}
    assert {r["kind"] for r in got["sql"]} >= {"checkpoint", "evaluation"}
    assert {r["id"] for r in got["runs"]} >= {capvector, sft}
    assert got["export"]["runs"]["rows"] == len(got["runs"])
    assert [v["status"] for v in got["verify"]] == ["ok"] and got["catalogue verify"]["ok"]
    assert {r["field"] for r in got["config show"]} >= {"name"} and got["vector stats"]
    mixed = CliRunner().invoke(
        app, ["--home", str(home), "lineage", capvector, "--json", "--format", "mermaid"]
    )
    assert mixed.exit_code == 2 and "--json prints JSON" in mixed.output


# The read-only commands and --help: none of these may be imported (issue 22: a query must not pay
# for torch, pandas, prefect or metaworld).
HEAVY = ("torch", "pandas", "prefect", "metaworld")
LIGHT_PROBE = """
import json, sys
HEAVY = json.loads(sys.argv[2])
from capvector.flows.cli.main import main
imported = {}
for args in json.loads(sys.argv[1]):
    sys.argv = ["capvector", *args]
    try:
        main()
        code = 0
    except SystemExit as e:
        code = e.code or 0
    imported[" ".join(args)] = [code, sorted(m for m in HEAVY if m in sys.modules)]
sys.stdout.flush()
print("\\nPROBE " + json.dumps(imported))
"""


def test_read_only_commands_import_neither_torch_pandas_prefect_nor_metaworld(tmp_path):
    home = tmp_path / "home"
    api = ArtifactsAPI(str(home))
    parent = api.register_json({"w": 1}, "checkpoint", "parent").id
    child = api.register_json({"w": 2}, "checkpoint", "child", parents=[(parent, "init")]).id
    commands = [
        ["--help"],
        ["sql", "SELECT kind, count(*) AS n FROM artifacts GROUP BY kind"],
        ["sql", "SELECT * FROM artifacts", "--json"],
        ["lineage", child[:12]],
        ["lineage", parent, "--descendants", "--format", "mermaid"],
        ["lineage", child, "--format", "json"],
        ["scores", parent[:12]],
        ["scores", parent, "--json"],
        ["artifacts", "list"],
        ["artifacts", "list", "--json"],
        ["artifacts", "show", child[:12]],
        ["verify", "--all"],
        ["verify", child],
        ["catalogue", "verify"],
        ["sql", "--help"],
        ["runs"],
        ["runs", "--format", "json", "--arm", "sft"],
        ["export", str(tmp_path / "export")],
        ["lineage", child, "--kinds", "checkpoint", "--format", "mermaid"],
    ]
    env = {**os.environ, "CAPVECTOR_HOME": str(home)}
    proc = subprocess.run(
        [sys.executable, "-c", LIGHT_PROBE, json.dumps(commands), json.dumps(HEAVY)],
        cwd=REPO, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    imported = json.loads(proc.stdout.rsplit("\nPROBE ", 1)[1])
    assert imported == {" ".join(c): [0, []] for c in commands}, proc.stderr
    assert "child" in proc.stdout and "parent" in proc.stdout


def test_sql_prints_whole_values_aligned_without_pandas(tmp_path):
    from capvector.flows.cli.common import text_table

    assert text_table(["a", "name"], [(1, "x"), (10, None)]).splitlines() == [
        " a  name",
        " 1  x",
        "10  NULL",
    ]
    long = "f" * 64
    assert long in text_table(["id"], [(long,)])  # pandas cut long strings short
    home = tmp_path / "home"
    out = CliRunner().invoke(app, ["--home", str(home), "sql", "SELECT 42 AS answer, 'x' AS s"])
    assert out.exit_code == 0 and out.stdout.splitlines() == ["answer  s", "    42  x"], out.stdout


def test_a_fully_cached_run_is_answered_before_any_flow_and_dry_run_shows_the_plan(smoke_home):
    """The cache answers the whole smoke plan in the CLI's process: same ids, no Prefect flow run
    (the runs table gains no row), and --dry-run lists each step, or the first one a change makes run."""
    home, ids = smoke_home
    api = ArtifactsAPI(str(home))
    runs_before = api.query_rows("SELECT count(*) FROM runs")[1][0][0]
    again = run_cli("run", "--preset", "smoke", "--json", home=home)
    assert json.loads(again.stdout) == ids
    log = max((home / "logs").glob("run-smoke-*.log"), key=lambda p: p.stat().st_mtime).read_text()
    assert "every one cached: answered without a flow run" in log
    assert ArtifactsAPI(str(home)).query_rows("SELECT count(*) FROM runs")[1][0][0] == runs_before
    dry = run_cli("run", "--preset", "smoke", "--dry-run", home=home).stdout
    assert dry.count("cached  ") == 34 and "all 34 steps cached" in dry
    artifacts_before = ArtifactsAPI(str(home)).query_rows("SELECT count(*) FROM artifacts")[1][0][0]
    changed = run_cli("run", "--preset", "smoke", "--set", "evaluation.horizon=31", "--dry-run", home=home)
    lines = changed.stdout.splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith("to run  "))
    assert lines[first] == "to run  validate θ_pt on D_ext"  # the horizon changes evaluations only
    listed = [line for line in lines if line.startswith(("cached  ", "to run  ", "then    "))]
    assert len(listed) == 34  # the whole plan, step by step
    assert re.search(r"\d+ of 34 steps to run or to look up once their inputs exist", changed.stdout)
    assert ArtifactsAPI(str(home)).query_rows("SELECT count(*) FROM artifacts")[1][0][0] == artifacts_before


def test_evaluate_with_video_registers_mp4s_of_the_evaluation_and_says_where(smoke_home, tmp_path):
    home, ids = smoke_home
    checkpoint = ids["checkpoints"]["sft/seed0"]
    args = ("evaluate", checkpoint, "--tasks", "reach-v3", "--episodes", "2", "--horizon", "15")
    with_video = json.loads(run_cli(*args, "--video", "1", "--json", home=home).stdout)
    without = json.loads(run_cli(*args, "--json", home=home).stdout)
    evaluation = with_video[0]["evaluation"]
    assert evaluation == without[0]["evaluation"]  # a video is not part of the protocol or the scores
    assert with_video[0]["success_rates"] == without[0]["success_rates"]
    api = ArtifactsAPI(str(home))
    _, rows = api.query_rows(
        "SELECT a.id, a.name, e.role FROM edges e JOIN artifacts a ON a.id = e.child "
        "WHERE e.parent = ? AND a.kind = 'video'",
        [evaluation],
    )
    assert len(rows) == 1 and rows[0][2] == "of" and "reach-v3 seed" in rows[0][1]
    video = rows[0][0]
    assert with_video[0]["videos"] == [{"name": rows[0][1], "id": video}]
    printed = run_cli(*args, "--video", "1", home=home).stdout  # cached: the same video
    assert f"capvector artifacts get {video[:12]} -o ." in printed and "reach-v3 seed" in printed
    copied = Path(run_cli("artifacts", "get", video[:12], "-o", str(tmp_path), home=home).stdout.strip())
    assert copied.suffix == ".mp4" and copied.read_bytes()[4:8] == b"ftyp"
    frames = iio.imread(copied, plugin="FFMPEG", index=None)
    seed = int(rows[0][1].rsplit(" ", 1)[1])
    (recorded,) = (e for e in json.loads(api.path(evaluation).read_text())["episodes"] if e["seed"] == seed)
    assert frames.shape == (recorded["steps"] + 1, 256, 256, 3)  # the reset, then one per step


def test_gif_videos_recorded_before_mp4s_are_still_listed_and_copied_out(tmp_path, capsys):
    """A home written when videos were GIFs: its videos are found with the new ones, and copied out."""
    from PIL import Image

    from capvector.flows.cli.experiment_commands import _print_videos
    from capvector.tasks.runtime.workspace import Workspace
    from capvector.tasks.steps.evaluation import VIDEO_KIND, video_ids_of, videos_of

    ws = Workspace(str(tmp_path / "home"))
    parent = ws.api.register_json({"stand-in": "evaluation"}, "report", "an evaluation")
    gif = tmp_path / "reach-v3-seed50000.gif"
    images = [Image.fromarray(np.full((64, 64, 3), shade, np.uint8)) for shade in (0, 128, 255)]
    images[0].save(gif, save_all=True, append_images=images[1:], duration=40, loop=0)  # as GIFs were
    old = ws.api.register_file(gif, VIDEO_KIND, "evaluate: reach-v3 seed 50000", parents=[(parent.id, "of")])
    assert video_ids_of(ws, [parent.id]) == {parent.id: [("evaluate: reach-v3 seed 50000", old.id)]}
    ((name, path),) = videos_of(ws, [parent.id])[parent.id]
    assert Image.open(path).n_frames == 3
    _print_videos(video_ids_of(ws, [parent.id]), None)
    printed = capsys.readouterr().out
    line = f"{parent.id[:12]}  evaluate: reach-v3 seed 50000   capvector artifacts get {old.id[:12]} -o ."
    assert line in printed
    listed = CliRunner().invoke(app, ["artifacts", "list", "--kind", "video", "--home", ws.home, "--json"])
    assert [row["id"] for row in json.loads(listed.stdout)] == [old.id]
    out = tmp_path / "out"
    out.mkdir()
    got = CliRunner().invoke(app, ["artifacts", "get", old.id[:12], "-o", str(out), "--home", ws.home])
    assert got.exit_code == 0 and (out / gif.name).read_bytes() == gif.read_bytes()
