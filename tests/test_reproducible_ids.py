"""Artifact ids are reproducible: the same work in two homes gives the same ids.

An id is the sha256 of an artifact's content, so no path, host, time, pid or random value may enter
the content; those are provenance and live in the sidecar record beside it. One fast test per place
that used to leak such a value into content (the vector files' metadata, the evaluation document, the
report). The end-to-end check, every artifact of a whole smoke run with the same id and record in two
homes, is tests/test_concurrent_runs.py (its lone run's home against the shared one).
"""

import json
from datetime import datetime

import torch

from capvector.core.evaluation.rollouts import EpisodeRecord, EvalConfig, EvalResult
from capvector.core.vectors.safetensors_io import Checkpoint, write_checkpoint
from capvector.tasks.runtime.workspace import Workspace, library_versions
from capvector.tasks.steps.evaluation import evaluation_doc
from capvector.tasks.steps.vectors import run_extract, run_merge

SHAPES = {"blocks.0.attn.weight": (6, 4), "blocks.0.attn.bias": (6,), "blocks.1.mlp.weight": (3, 6)}


def _checkpoint(path, seed: int):
    gen = torch.Generator().manual_seed(seed)
    write_checkpoint(path, {k: torch.randn(s, generator=gen) for k, s in SHAPES.items()})
    return path


def _homes(tmp_path) -> list[Workspace]:
    return [Workspace(str(tmp_path / name)) for name in ("home_a", "home_b")]


def test_vector_and_merge_steps_give_the_same_ids_in_two_homes(tmp_path):
    """γ and θ_meta used to carry the absolute store paths of their inputs in their metadata."""
    files = {n: _checkpoint(tmp_path / f"{n}.safetensors", s) for n, s in [("pt", 0), ("ft", 1), ("ao", 2)]}
    ids = []
    for ws in _homes(tmp_path):
        inputs = {n: ws.api.register_file(p, kind="checkpoint", name=n).id for n, p in files.items()}
        vector = run_extract(
            ws, "γ", {"minuend": inputs["ao"], "subtrahend": inputs["ft"], "base": inputs["pt"]}, {}
        )
        meta = run_merge(ws, "θ_meta", {"base": inputs["pt"], "vector": vector}, {"alpha": 1.1})
        stats = ws.api.query("SELECT DISTINCT stats_id FROM vector_stats")["stats_id"].tolist()
        for artifact in (vector, meta):
            header = json.dumps(Checkpoint(ws.path(artifact)).metadata)
            assert ws.home not in header and str(tmp_path) not in header, header
        ids.append((vector, meta, stats))
    assert ids[0] == ids[1]


def _result(wall_time_s: float) -> EvalResult:
    config = EvalConfig(tasks=["reach-v3"], episodes_per_task=2, horizon=5)
    episodes = [EpisodeRecord(task="reach-v3", seed=100000 + i, success=i == 0, steps=5, episode_return=1.5)
                for i in range(2)]  # fmt: skip
    return EvalResult(
        config=config,
        fingerprint="f" * 64,
        protocol={"camera": "corner2"},
        versions={"mujoco": "3.3.0"},
        episodes=episodes,
        success_rates={"reach-v3": 0.5},
        mean_success=0.5,
        env_steps=10,
        policy_calls=4,
        wall_time_s=wall_time_s,
        videos={"reach-v3": f"/tmp/videos-{wall_time_s}/reach.mp4"},
    )


def test_an_evaluation_gives_the_same_id_in_two_homes_and_at_two_times(tmp_path):
    """The document used to carry `evaluated_at` (added by the store's EvaluationDoc): a time in
    content. When it ran is the sidecar's `created_at`."""
    ckpt = _checkpoint(tmp_path / "ckpt.safetensors", 0)
    ids = []
    for ws, wall in zip(_homes(tmp_path), (1.0, 2.0), strict=True):
        checkpoint = ws.api.register_file(ckpt, kind="checkpoint", name="ckpt").id
        doc = evaluation_doc(checkpoint, _result(wall), library_versions())
        assert not {"evaluated_at", "wall_time_s", "videos"} & set(doc), doc
        record = ws.api.register_evaluation(doc, name="evaluate", config={"wall_time_s": wall})
        stored = ws.api.store.open_json(record.id)
        assert "evaluated_at" not in stored, stored
        assert record.created_at  # when it ran: in the sidecar
        ids.append(record.id)
    assert ids[0] == ids[1]


def test_an_old_report_shows_the_measured_speeds_from_the_checkpoints_records(tmp_path):
    """A report never held each run's steps/s, ms/step and wall time (a measurement of the machine and
    its load): `capvector report` of an old report reads them from the checkpoints' records."""
    from conftest import old_report

    from capvector.flows.recipe.report import write_report

    ckpt = _checkpoint(tmp_path / "ckpt.safetensors", 0)
    for ws, speed in zip(_homes(tmp_path), (10.0, 40.0), strict=True):
        summary = {"steps": 20, "steps_per_s": speed, "trainable_parameters": 123}
        config = {"summary": summary, "train_step": {"train": {"lr": 3e-4, "steps": 20}}}
        checkpoint = ws.api.register_file(ckpt, kind="checkpoint", name="sft", config=config).id
        doc = {**evaluation_doc(checkpoint, _result(1.0), {}), "evaluated_at": datetime(2026, 1, 1)}
        evaluation = ws.api.register_evaluation(
            doc, name="evaluate", config={"success_rates": {"reach-v3": 0.5}, "mean_success": 0.5}
        ).id
        report = old_report(ws, {"sft/seed0": evaluation})
        text = write_report(ws, report, tmp_path / ws.home / "report.md").read_text()
        assert f"| {1000 / speed:.1f} | {20 / speed:.0f} | 123 | 0.0003 | 1 |" in text  # from the sidecar
