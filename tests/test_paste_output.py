"""Issue 37, item 5: what the read commands print can be pasted. Written to a pipe, no path, id or task
name is wrapped or cut (rich wraps at 80 columns when it sees no terminal); a merge's α is on its vector
edge in the lineage views."""

from __future__ import annotations

import torch
from safetensors.torch import save_file
from typer.testing import CliRunner

from capvector.flows.cli import common as cli_common
from capvector.flows.cli.main import app
from capvector.tasks.runtime.workspace import Workspace

TASKS = ["button-press-topdown-wall-v3", "button-press-wall-v3", "button-press-v3"]


def cli(home, *args: str) -> str:
    cli_common.console._console = None  # made again for this (non-terminal) stdout
    result = CliRunner().invoke(app, ["--home", str(home), *args])
    assert result.exit_code == 0, (result.output, result.exception)
    return result.stdout


def _checkpoints(folder) -> dict[str, str]:
    paths = {}
    for i, name in enumerate(("pt", "ft", "ao")):
        g = torch.Generator().manual_seed(i)
        paths[name] = str(folder / f"{name}.safetensors")
        save_file({"a.weight": torch.randn(4, 3, generator=g)}, paths[name])
    return paths


def test_scores_in_a_pipe_print_whole_task_names_and_ids(tmp_path):
    ws = Workspace(str(tmp_path / "home"))
    checkpoint = ws.api.register_json({"w": 1}, "checkpoint", "downstream capvector draw 0 seed 0").id
    episodes = [
        {"task": t, "seed": 100000 + i, "success": i == 0, "steps": 5, "return": 0.0}
        for t in TASKS
        for i in range(2)
    ]
    doc = {"checkpoint_id": checkpoint, "fingerprint": "f" * 64, "episodes": episodes}
    ws.api.register_evaluation(doc, name="evaluate", config={})
    out = cli(ws.home, "scores", checkpoint)
    for task in TASKS:
        (line,) = [line for line in out.splitlines() if f" {task} " in line]
        assert checkpoint[:12] in line and "50.0%" in line  # one row, one line, whole
    assert "…" not in out


def test_a_long_output_path_and_its_id_stay_on_one_line(tmp_path):
    p = _checkpoints(tmp_path)
    deep = tmp_path / ("a-folder-with-a-long-name-" * 4) / "capability-vector-of-the-first-draw.safetensors"
    deep.parent.mkdir(parents=True)
    out = cli(tmp_path / "home", "vector", "extract", p["ao"], p["ft"], "-o", str(deep))
    (line,) = out.splitlines()
    assert line.startswith(str(deep)) and len(line.split("(artifact ")[1].rstrip(")")) == 64


def test_a_merge_has_its_alpha_on_the_vector_edge_of_its_lineage(tmp_path):
    home, p = tmp_path / "home", _checkpoints(tmp_path)
    gamma, merged = tmp_path / "gamma.safetensors", tmp_path / "merged.safetensors"
    cli(home, "vector", "extract", p["ao"], p["ft"], "-o", str(gamma))
    text = cli(home, "vector", "merge", p["pt"], "--vector", str(gamma), "--alpha", "0.5", "-o", str(merged))
    merged_id = text.split("(artifact ")[1].split(")")[0]
    mermaid = cli(home, "lineage", merged_id, "--format", "mermaid")
    assert "-->|vector α=0.5|" in mermaid and "-->|base|" in mermaid
    tree = cli(home, "lineage", merged_id)
    assert "(vector α=0.5) vector gamma" in tree
