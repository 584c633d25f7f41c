"""Benchmark: time per training step of CapVector (SFT + orthogonal loss) and auxiliary SFT, vs SFT.

The issue's bar is CapVector at ≤ 1.1× SFT's time per step. The study's own timings come from runs
that share 2 cores with other steps, so they are rough; here the three recipes train the same model
from the same weights on the same batches, in alternating order in one process (SFT, CapVector, aux,
then reversed), so load drifts hit all alike. The orthogonal loss uses a random γ of realistic size
(θ_ao − θ_ft is dense); the aux objective is `dynamics`, as in the state studies. Ratio = median over
rounds of (recipe seconds / SFT seconds), each round's runs adjacent in time.

`--before REV` adds a fourth recipe, `capvector_before`: CapVector with the `OrthogonalRegularizer` of
`capvector_core/training/orthogonal.py` as committed at git revision REV (read with `git show`, loaded as a
module; nothing in the working tree changes), so an optimisation's before and after come from the same
run, alternating like the others.

    python benchmarks/bench_step_cost.py --steps 200 --rounds 5 [--before REV] [--models study-large]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import torch

from capvector.core.policies.base import build_policy
from capvector.core.training.orthogonal import OrthogonalRegularizer
from capvector.core.training.trainer import AuxConfig, TrainConfig, train

ROOT = Path(__file__).resolve().parent
RESULTS = ROOT / "results"
RECIPES = ("sft", "capvector", "aux")
MODELS = {"study-small": (64, 2), "study-large": (128, 4)}
REGULARIZERS = {"capvector": OrthogonalRegularizer}


def regularizer_at(rev: str, work: Path) -> type:
    """`OrthogonalRegularizer` as committed at git revision `rev` (a module loaded from `git show`)."""
    repo = ROOT.parent
    source = subprocess.run(
        ["git", "show", f"{rev}:capvector_core/training/orthogonal.py"], cwd=repo, check=True,
        capture_output=True,
    ).stdout
    path = work / "orthogonal_before.py"
    path.write_bytes(source)
    spec = importlib.util.spec_from_file_location("orthogonal_before", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.OrthogonalRegularizer


def run(recipe: str, spec: dict, initial: dict, dataset, config: TrainConfig, work: Path) -> float:
    policy = build_policy(spec, "cpu")
    policy.load_state_dict(initial)
    extra = {}
    if recipe in REGULARIZERS:
        generator = torch.Generator().manual_seed(1)
        gamma = {
            k: 1e-3 * torch.randn(v.shape, generator=generator)
            for k, v in initial.items()
            if v.is_floating_point()
        }
        extra["orthogonal"] = REGULARIZERS[recipe](policy, gamma, initial, weight=1e-2)
    if recipe == "aux":
        config = config.model_copy(update={"aux": AuxConfig(name="dynamics", weight=0.5)})
    start = time.perf_counter()
    train(policy, dataset, config, work / f"{recipe}-{time.monotonic_ns()}", extra_losses=extra)
    return time.perf_counter() - start


def measure(
    name: str, d_model: int, layers: int, dataset, config: TrainConfig, rounds: int, work: Path, recipes
) -> dict:
    spec = {"type": "l1_chunk", "d_model": d_model, "n_layers": layers, "n_heads": 4, "chunk_size": 8}
    torch.manual_seed(0)
    initial = build_policy(spec, "cpu").state_dict()
    warm = config.model_copy(update={"steps": 5, "warmup_steps": 1})
    for recipe in recipes:  # untimed: one-time lazy work inside torch
        run(recipe, spec, initial, dataset, warm, work)
    seconds: dict[str, list[float]] = {r: [] for r in recipes}
    for r in range(rounds):
        for recipe in recipes if r % 2 == 0 else recipes[::-1]:
            seconds[recipe].append(run(recipe, spec, initial, dataset, config, work))
        print(f"{name} round {r}: " + ", ".join(f"{k} {v[-1]:.2f} s" for k, v in seconds.items()))
    ratio = {
        recipe: statistics.median(t / s for t, s in zip(seconds[recipe], seconds["sft"], strict=True))
        for recipe in recipes
    }
    return {
        "model": spec,
        "seconds": {k: [round(x, 3) for x in v] for k, v in seconds.items()},
        "ms_per_step": {k: round(1000 * statistics.median(v) / config.steps, 2) for k, v in seconds.items()},
        "ratio_to_sft": {k: round(v, 3) for k, v in ratio.items()},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--work-dir", type=Path, default=None, help="demo cache (default: bench_learning's)")
    ap.add_argument(
        "--before", metavar="REV", default=None, help="also time CapVector with orthogonal.py as of git REV"
    )
    ap.add_argument("--models", nargs="+", choices=list(MODELS), default=list(MODELS))
    args = ap.parse_args()
    torch.set_num_threads(1)
    from bench_learning import WORK, demos  # cached 8-task state demos

    dataset, _ = demos("state", 5, 64, args.work_dir or WORK)
    config = TrainConfig(
        steps=args.steps,
        batch_size=64,
        warmup_steps=args.steps // 10,
        checkpoint_every=args.steps,
        log_every=10,
        device="cpu",
        num_threads=1,
    )
    work = Path(tempfile.mkdtemp(prefix="bench-step-cost-"))
    recipes = RECIPES
    if args.before:
        args.before = subprocess.run(  # a commit, not a moving name, in the results
            ["git", "rev-parse", "--short", args.before],
            cwd=ROOT.parent,
            check=True,
            capture_output=True,
            text=True,
        ).stdout.strip()
        REGULARIZERS["capvector_before"] = regularizer_at(args.before, work)
        recipes = ("sft", "capvector_before", "capvector", "aux")
    try:
        results = {
            name: measure(name, *MODELS[name], dataset, config, args.rounds, work, recipes)
            for name in args.models
        }
    finally:
        shutil.rmtree(work, ignore_errors=True)
    entry = {
        "steps_per_run": args.steps,
        "rounds": args.rounds,
        "batch_size": 64,
        "torch_threads": 1,
        "target_capvector_ratio": 1.1,
        "before_rev": args.before,
        "models": results,
    }
    print(json.dumps(entry, indent=1))
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "step_cost.json").write_text(json.dumps(entry, indent=1) + "\n")
    before = bool(args.before)
    rows = ""
    for name, e in results.items():
        ms, ratio, model = e["ms_per_step"], e["ratio_to_sft"], e["model"]
        rows += f"| {name} | d={model['d_model']}, {model['n_layers']} layers | {ms['sft']} | "
        rows += f"{ms['capvector_before']} | " if before else ""
        rows += f"{ms['capvector']} | {ms['aux']} | "
        rows += f"{ratio['capvector_before']:.2f}× | " if before else ""
        rows += f"**{ratio['capvector']:.2f}×** | {ratio['aux']:.2f}× |\n"
    command = f"benchmarks/bench_step_cost.py --steps {args.steps} --rounds {args.rounds}"
    command += f" --before {args.before}" if before else ""
    command += f" --models {' '.join(args.models)}" if args.models != list(MODELS) else ""
    head = "| model | size | SFT ms/step | "
    head += f"CapVector at {args.before} ms/step | " if before else ""
    head += "CapVector ms/step | aux ms/step | "
    head += f"CapVector at {args.before} / SFT | " if before else ""
    head += "CapVector / SFT | aux / SFT |\n"
    (RESULTS / "step_cost.md").write_text(
        "# Time per training step: CapVector and auxiliary SFT vs SFT\n\n"
        f"`{command}`: same model, weights and batches, recipes alternating in one process, 1 torch "
        "thread, batch 64, whole `train` calls. "
        "Ratio: median over rounds of recipe time / SFT time (target for CapVector: ≤ 1.1×)."
        + (
            f" `CapVector at {args.before}`: the orthogonal regularizer as committed at that revision, "
            "timed in the same run."
            if before
            else ""
        )
        + "\n\n"
        + head
        + "|---" * (head.count("|") - 1)
        + "|\n"
        + rows
    )


if __name__ == "__main__":
    main()
