"""Trainer: learning, validation errors, NaN, extra-loss hook, pixels path, exact resume after SIGKILL."""

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch

from capvector.core.policies import L1ChunkConfig, L1ChunkPolicy
from capvector.core.policies.base import build_policy, load_policy
from capvector.core.simulation.demos import DatasetMeta, DemoDataset
from capvector.core.training.batching import SampleTable
from capvector.core.training.trainer import AuxConfig, TrainConfig, lr_at, train

TINY = dict(d_model=32, n_layers=2, n_heads=4, chunk_size=4, vocab_size=64, max_instruction_tokens=6)
REPO = Path(__file__).resolve().parents[1]


def make_dataset(obs_mode="state", episodes=4, length=20, image_size=16, privileged=True, seed=0):
    """A contract-shaped DemoDataset whose actions are a smooth function of the state (learnable)."""
    g = torch.Generator().manual_seed(seed)
    n = episodes * length
    state = torch.randn(n, 39, generator=g)
    tensors = {
        "state": state,
        "proprio": state[:, :4].clone(),
        "action": torch.tanh(state[:, :4] + 0.5 * state[:, 35:39]),
        "episode": torch.arange(episodes).repeat_interleave(length),
        "step": torch.arange(length).repeat(episodes),
        "task": (torch.arange(episodes) % 2).repeat_interleave(length),
    }
    if privileged:
        tensors["privileged"] = state[:, 4:13].clone()
    if obs_mode == "pixels":
        tensors["image"] = torch.randint(
            0, 256, (n, image_size, image_size, 3), generator=g, dtype=torch.uint8
        )
    tasks = ["reach-v3", "push-v3"]
    meta = DatasetMeta(
        tasks=tasks,
        instructions=["reach to the goal", "push the puck to the goal"],
        obs_mode=obs_mode,
        camera="corner2",
        image_size=image_size,
        horizon=length,
        episodes_per_task=episodes // 2,
        seed_offset=0,
        seeds={t: list(range(episodes // 2)) for t in tasks},
        failures={t: 0 for t in tasks},
        n_episodes=episodes,
        n_steps=n,
    )
    return DemoDataset.create(tensors, meta)


def quick(**kw) -> TrainConfig:
    base = dict(steps=30, batch_size=16, lr=3e-3, warmup_steps=5, checkpoint_every=1000, log_every=5)
    # one thread: tiny models gain nothing from two, and two crawl when other jobs share the cores
    base.update(device="cpu", num_threads=1)
    return TrainConfig(**{**base, **kw})


def curve(path) -> list[dict]:
    return [json.loads(line) for line in Path(path).read_text().splitlines()]


def test_progress_reports_each_logged_step_with_its_loss(tmp_path):
    """The trainer only reports; capvector.tasks.runtime.progress decides where the lines go."""
    calls = []
    policy = L1ChunkPolicy(L1ChunkConfig(**TINY))
    train(policy, make_dataset(), quick(steps=20, log_every=5), tmp_path, progress=lambda *a: calls.append(a))
    assert [(done, total) for done, total, _ in calls] == [(0, 20), (5, 20), (10, 20), (15, 20), (20, 20)]
    assert calls[0][2] == "started" and all(detail.startswith("loss ") for *_, detail in calls[1:]), calls


@pytest.mark.parametrize("policy_type", ["l1_chunk", "flow"])
def test_loss_decreases_and_outputs_written(tmp_path, policy_type):
    torch.manual_seed(0)
    policy = build_policy({"type": policy_type, **TINY}, "cpu")
    result = train(policy, make_dataset(), quick(steps=120), tmp_path)
    rows = curve(result.loss_curve_path)
    assert rows[-1]["step"] == 120 and {"loss", "action", "lr", "time", "grad_norm"} <= set(rows[0])
    # flow matching's loss keeps the noise's irreducible variance: it falls less far
    assert rows[-1]["loss"] < {"l1_chunk": 0.6, "flow": 0.8}[policy_type] * rows[0]["loss"]
    assert policy.generator is None  # the run's generator was the run's: after it, the global RNG again
    loaded = load_policy(result.weights_path, device="cpu")
    assert bool(loaded.normalizer.fitted)
    for k, v in policy.state_dict().items():
        assert torch.equal(v, loaded.state_dict()[k])
    assert result.samples_per_s > 0


def test_sample_table_stays_within_episode():
    ds = make_dataset(episodes=2, length=5)
    table = SampleTable(ds.tensors, chunk_size=3, horizon=2)
    assert table.chunk[3].tolist() == [3, 4, 4]  # last action of episode 0 repeats
    assert table.chunk[5].tolist() == [5, 6, 7]
    assert table.future[4].item() == 4 and table.future[5].item() == 7
    shuffled = {**ds.tensors, "step": ds.tensors["step"].flip(0)}
    with pytest.raises(ValueError, match="grouped by episode"):
        SampleTable(shuffled, 3, None)


def test_lr_schedule():
    cfg = TrainConfig(steps=100, lr=1.0, warmup_steps=10, min_lr_ratio=0.1)
    assert lr_at(0, cfg) == pytest.approx(0.1) and lr_at(9, cfg) == pytest.approx(1.0)
    assert lr_at(10, cfg) == pytest.approx(1.0) and lr_at(100, cfg) == pytest.approx(0.1)


def test_validation_errors(tmp_path):
    policy = L1ChunkPolicy(L1ChunkConfig(**TINY))
    with pytest.raises(ValueError, match=r"batch_size \(500\) is larger than the dataset \(80"):
        train(policy, make_dataset(), quick(batch_size=500), tmp_path)
    with pytest.raises(ValueError, match=r"'spatial' needs dataset field\(s\) \['privileged'\]"):
        train(
            policy,
            make_dataset(privileged=False),
            quick(aux=AuxConfig(name="spatial")),
            tmp_path,
        )
    with pytest.raises(ValueError, match="unknown auxiliary objective 'depth'.*dynamics.*spatial"):
        AuxConfig(name="depth")
    with pytest.raises(ValueError, match="collide"):
        train(policy, make_dataset(), quick(), tmp_path, extra_losses={"action": lambda m: 0})


def test_nan_loss_names_step_and_term(tmp_path):
    policy = L1ChunkPolicy(L1ChunkConfig(**TINY))
    calls = []

    def sometimes_nan(model):
        calls.append(1)
        return torch.tensor(float("nan")) if len(calls) == 3 else torch.zeros(())

    with pytest.raises(FloatingPointError, match=r"step 2: term\(s\) \['loss', 'bad'\]"):
        train(policy, make_dataset(), quick(), tmp_path, extra_losses={"bad": sometimes_nan})


def test_extra_loss_hook_is_called_and_logged(tmp_path):
    policy = L1ChunkPolicy(L1ChunkConfig(**TINY))
    seen = []

    def l2(model):
        seen.append(model)
        return 1e-3 * sum(p.pow(2).sum() for p in model.action_head.parameters())

    result = train(policy, make_dataset(), quick(steps=10), tmp_path, extra_losses={"l2": l2})
    assert len(seen) == 10 and seen[0] is policy
    rows = curve(result.loss_curve_path)
    assert all(r["l2"] > 0 for r in rows)
    assert rows[0]["loss"] == pytest.approx(rows[0]["action"] + rows[0]["l2"], rel=1e-5)


def test_pixels_path_trains(tmp_path):
    config = L1ChunkConfig(obs_mode="pixels", image_size=16, stem_channels=[8, 16], **TINY)
    result = train(
        L1ChunkPolicy(config),
        make_dataset("pixels"),
        quick(steps=6, aux=AuxConfig(name="spatial")),
        tmp_path,
    )
    rows = curve(result.loss_curve_path)
    assert rows[-1]["step"] == 6 and "spatial" in rows[-1]
    with pytest.raises(ValueError, match="images are"):
        bigger = L1ChunkConfig(obs_mode="pixels", image_size=32, stem_channels=[8, 16], **TINY)
        train(L1ChunkPolicy(bigger), make_dataset("pixels"), quick(), tmp_path / "x")


def _trained(policy_type: str, dropout: float, aux: AuxConfig | None, run_dir: Path) -> dict:
    torch.manual_seed(0)  # θ_pt: the same start for both runs
    policy = build_policy({"type": policy_type, "dropout": dropout, **TINY}, "cpu")
    result = train(policy, make_dataset(), quick(steps=8, seed=3, aux=aux), run_dir)
    return {"weights": policy.state_dict(), "curve": curve(result.loss_curve_path)}


@pytest.mark.parametrize("policy_type", ["l1_chunk", "flow"])
@pytest.mark.parametrize("dropout", [0.0, 0.1])
def test_an_objective_of_weight_zero_gives_theta_ft_bit_for_bit(tmp_path, policy_type, dropout):
    """γ = θ_ao − θ_ft needs the two runs to differ by the objective alone: same start, seed, batches,
    and the same draws of the policy's own randomness (flow matching's noise and times, dropout), which
    come from the run's generator, not from torch's global RNG, which the objective's heads' initialisation
    used to consume. With the objective present but weighted 0, θ_ao is θ_ft bit for bit (the flow
    backbone's θ_ao drew other noise and times before, and every backbone's other dropout masks)."""
    ft = _trained(policy_type, dropout, None, tmp_path / "ft")
    aux = AuxConfig(name="dynamics", weight=0.0, params={"horizon": 3})
    ao = _trained(policy_type, dropout, aux, tmp_path / "ao")
    assert ao["weights"].keys() == ft["weights"].keys()
    differ = [k for k, v in ft["weights"].items() if not torch.equal(v, ao["weights"][k])]
    assert not differ, differ
    assert [r["action"] for r in ao["curve"]] == [r["action"] for r in ft["curve"]]
    assert all(r["dynamics"] == 0.0 for r in ao["curve"])  # logged (as weight × loss), not trained
    weighted = _trained(policy_type, dropout, aux.model_copy(update={"weight": 0.5}), tmp_path / "w")
    assert any(not torch.equal(v, weighted["weights"][k]) for k, v in ft["weights"].items())


RUNNER = textwrap.dedent(
    """
    import sys, torch
    sys.path.insert(0, {tests!r})
    from test_trainer import TINY, make_dataset, quick
    from capvector.core.policies.base import build_policy
    from capvector.core.training.trainer import AuxConfig, train
    torch.set_num_threads(1)
    torch.manual_seed(1)
    policy = build_policy({{"type": sys.argv[2], "dropout": 0.1, **TINY}}, "cpu")
    aux = AuxConfig(name="dynamics", params={{"horizon": 3}})
    cfg = quick(steps=300, checkpoint_every=25, seed=7, aux=aux)
    train(policy, make_dataset(), cfg, sys.argv[1])
    """
)


@pytest.mark.parametrize("policy_type", ["l1_chunk", "flow"])  # flow also draws noise and times
def test_resume_after_sigkill_is_bit_identical(tmp_path, policy_type):
    script = tmp_path / "run.py"
    script.write_text(RUNNER.format(tests=str(REPO / "tests")))
    env = {**os.environ, "PYTHONPATH": str(REPO)}

    def run(run_dir):
        args = [sys.executable, str(script), str(run_dir), policy_type]
        subprocess.run(args, check=True, env=env, cwd=REPO)

    killed = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, str(script), str(killed), policy_type], env=env, cwd=REPO)
    deadline = time.time() + 120
    while not list((killed / "checkpoints").glob("step_*")) and time.time() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (killed / "policy.safetensors").exists(), "run finished before the kill; make it longer"
    steps_at_kill = sorted(p.name for p in (killed / "checkpoints").glob("step_*"))
    assert steps_at_kill and steps_at_kill[-1] < "step_00000300"
    run(killed)
    straight = tmp_path / "straight"
    run(straight)
    a = load_policy(killed / "policy.safetensors", device="cpu").state_dict()
    b = load_policy(straight / "policy.safetensors", device="cpu").state_dict()
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k
    from safetensors.torch import load_file

    ha, hb = load_file(killed / "aux_heads.safetensors"), load_file(straight / "aux_heads.safetensors")
    assert all(torch.equal(ha[k], hb[k]) for k in ha)
    result = json.loads((killed / "result.json").read_text())
    assert result["resumed_from_step"] > 0
    assert [r["step"] for r in curve(killed / "loss_curve.jsonl")] == [
        r["step"] for r in curve(straight / "loss_curve.jsonl")
    ]


def fresh_policy() -> L1ChunkPolicy:
    torch.manual_seed(0)
    return L1ChunkPolicy(L1ChunkConfig(**TINY))


def test_resume_refuses_a_different_config(tmp_path):
    train(fresh_policy(), make_dataset(), quick(steps=10, checkpoint_every=5), tmp_path)
    cfg = quick(steps=10, checkpoint_every=5, log_every=2)
    again = train(fresh_policy(), make_dataset(), cfg, tmp_path)
    assert again.resumed_from_step == 10  # finished run: nothing left to do, log_every may differ
    with pytest.raises(ValueError, match=r"differs in \['lr'\]"):
        train(fresh_policy(), make_dataset(), quick(steps=10, lr=1e-2), tmp_path)


def test_resume_refuses_another_runs_checkpoints(tmp_path):
    """A run_dir reused for other data or another start is an error, not someone else's weights."""
    config = quick(steps=10, checkpoint_every=5)
    first = train(fresh_policy(), make_dataset(), config, tmp_path)
    weights = (tmp_path / "policy.safetensors").read_bytes()
    with pytest.raises(ValueError, match=r"its data \(.*\) differ; this run_dir belongs to another run"):
        train(fresh_policy(), make_dataset(seed=1), config, tmp_path)
    trained = fresh_policy()
    train(trained, make_dataset(), quick(steps=6, checkpoint_every=3), tmp_path / "other")
    with pytest.raises(ValueError, match=r"its start \(.*\) differ"):
        train(trained, make_dataset(), config, tmp_path)  # starts from trained weights: another run
    assert (tmp_path / "policy.safetensors").read_bytes() == weights  # nothing stored was touched
    assert train(fresh_policy(), make_dataset(), config, tmp_path).resumed_from_step == first.steps


def test_snapshots_are_the_weights_at_their_step_and_bad_ones_refused(tmp_path):
    model = build_policy(L1ChunkConfig(obs_mode="state", d_model=32, n_layers=1, n_heads=2, chunk_size=4))
    config = quick(steps=12, checkpoint_every=4, keep_checkpoints=10, snapshot_steps=[4, 8])
    result = train(model, make_dataset(), config, tmp_path / "run")
    assert sorted(result.snapshots) == [4, 8]
    for step, path in result.snapshots.items():
        kept = load_policy(path).state_dict()
        at_checkpoint = load_policy(
            tmp_path / "run" / "checkpoints" / f"step_{step:08d}" / "policy.safetensors"
        )
        assert all(torch.equal(v, at_checkpoint.state_dict()[k]) for k, v in kept.items())
    early, later = (load_policy(result.snapshots[s]).state_dict() for s in (4, 8))
    assert any(not torch.equal(early[k], later[k]) for k in early)  # two budgets, two different policies
    for bad in ([12], [0], [4, 4]):
        with pytest.raises(ValueError, match="snapshot_steps"):
            quick(steps=12, snapshot_steps=bad)


def _as_if_killed_after(run_dir: Path, step: int) -> None:
    """The run dir a kill -9 leaves once checkpoint `step` was written: later checkpoints, the final
    weights and the result are not there yet."""
    for ckpt in (run_dir / "checkpoints").glob("step_*"):
        if int(ckpt.name.split("_")[1]) > step:
            shutil.rmtree(ckpt)
    for name in ("policy.safetensors", "result.json"):
        (run_dir / name).unlink()


@pytest.mark.parametrize("lost", ["snapshot", "trainer_state", "loss_curve", "policy_generator"])
def test_a_resume_recomputes_what_was_lost_from_the_run_dir(tmp_path, lost):
    """A file removed from an interrupted run dir (a snapshot, a checkpoint's state or the policy
    generator's state in it, the loss curve) is recomputed from the newest intact checkpoint before it,
    or from the start: never a dead end, and the result is bit for bit an uninterrupted run's."""
    config = quick(steps=12, checkpoint_every=4, keep_checkpoints=10, snapshot_steps=[4, 8])

    def fresh():
        torch.manual_seed(0)
        return L1ChunkPolicy(L1ChunkConfig(**TINY))

    straight = train(fresh(), make_dataset(), config, tmp_path / "straight")
    run_dir = tmp_path / "run"
    train(fresh(), make_dataset(), config, run_dir)
    _as_if_killed_after(run_dir, 8)
    if lost == "snapshot":  # resuming at 8 would never write the snapshot at 4 again
        (run_dir / "snapshots" / "step_00000004.safetensors").unlink()
    elif lost == "trainer_state":
        (run_dir / "checkpoints" / "step_00000008" / "trainer_state.pt").unlink()
    elif lost == "policy_generator":  # a checkpoint from before the policy drew from its own generator
        state_path = run_dir / "checkpoints" / "step_00000008" / "trainer_state.pt"
        state = torch.load(state_path, weights_only=True)
        del state["sampling"], state["sampling_device"]
        torch.save(state, state_path)
    else:
        (run_dir / "loss_curve.jsonl").unlink()
    lines: list[str] = []
    result = train(fresh(), make_dataset(), config, run_dir, progress=lambda d, t, x="": lines.append(x))
    assert result.resumed_from_step == (0 if lost == "loss_curve" else 4)
    assert "passed over" in lines[0], lines[0]
    assert result.weights_path.read_bytes() == straight.weights_path.read_bytes()
    for step, path in straight.snapshots.items():
        assert result.snapshots[step].read_bytes() == path.read_bytes(), step
    steps = [r["step"] for r in curve(result.loss_curve_path)]
    assert steps == [r["step"] for r in curve(straight.loss_curve_path)]
