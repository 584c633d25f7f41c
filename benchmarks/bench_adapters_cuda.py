"""The fine-tuning forms on a GPU: steps/s against full fine-tuning, and exact resume of the stateful ones.

The studies fine-tune the l1_chunk policy (d_model 128 × 4 layers) in four forms: full weights, LoRA,
LoRA-SP and AdaLoRA (capvector.tasks.adapters). On the project's CPU machine their cost was measured
(`bench_adapters.py`); on a GPU the picture differs (small kernels: each adapted layer adds launches, and
AdaLoRA's rank allocation runs Python over every adapted tensor after each step). This script checks, in
one short run on a lent GPU:

1. steps/s of `train` per form, full / LoRA r 8 / LoRA r 64 / LoRA-SP bank 32 / AdaLoRA (the studies'
   settings, flows/recipe/config.py, besides the r 64 row), the trainable parameters, and each form's
   steps/s as a share of full fine-tuning's in the same run (rounds alternate the order of the forms);
2. exact resume on the device for LoRA-SP and AdaLoRA (AdaLoRA's allocator state is checkpointed through
   the trainer's `after_optimizer_step` hook): a run interrupted after a checkpoint (its `on_checkpoint`
   raises) and resumed, against an uninterrupted one, beside two uninterrupted runs against each other
   (the floor set by non-deterministic CUDA kernels).

Each form is applied as the training step applies it (capvector.tasks.steps.training._train_checkpoint):
the fields of a `TrainStepConfig`, `ADAPTERS[name].apply(model, step_config)` after seeding with the
run's seed, the form's `extra_losses()`, and its `after_optimizer_step(model)` hook passed to `train`.
The data is bench_train_cuda's synthetic DemoDataset, so no Meta-World rollouts (or rendering) are
needed. Results are written to results/adapters_cuda.{md,json} (or --results); a `--quick` dry run
writes them only with `--write`.

    MUJOCO_GL=disable PYTHONPATH=.:benchmarks python benchmarks/bench_adapters_cuda.py --device cuda
    PYTHONPATH=.:benchmarks python benchmarks/bench_adapters_cuda.py --device cpu --quick   # dry run
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import torch
from bench_train_cuda import (
    Interrupted,
    add_device_options,
    compared,
    cpu_state,
    difference,
    entry_of,
    make_dataset,
    say,
    timed,
    write_results,
)

from capvector.core.adapters import adalora
from capvector.core.adapters.adalora import AdaLoraConfig
from capvector.core.adapters.lora import LoraConfig, trainable_parameter_count
from capvector.core.adapters.lora_sp import LoraSPConfig
from capvector.core.policies.base import build_policy
from capvector.core.simulation.demos import DemoDataset
from capvector.core.training.device import resolve_device, run_environment
from capvector.core.training.trainer import TrainConfig, train
from capvector.tasks.adapters import ADAPTERS

TARGETS = ["attn.*_proj", "mlp.fc*", "action_head.*"]  # the studies' adapter targets (flows/recipe/config)
FORMS: dict[str, dict[str, Any]] = {
    "full": {"adapter": "full"},
    "lora r8": {"adapter": "lora", "lora": LoraConfig(target_modules=TARGETS, r=8)},
    "lora r64": {"adapter": "lora", "lora": LoraConfig(target_modules=TARGETS, r=64)},
    "lora_sp bank32": {"adapter": "lora_sp", "lora_sp": LoraSPConfig(target_modules=TARGETS, bank_size=32)},
    "adalora": {"adapter": "adalora", "adalora": AdaLoraConfig(target_modules=TARGETS)},
}
RESUMED = ["lora_sp bank32", "adalora"]


def policy_spec(args) -> dict[str, Any]:
    return {"type": "l1_chunk", "d_model": args.d_model, "n_layers": 4, "n_heads": 4, "chunk_size": 8}


class StepConfig(SimpleNamespace):
    """The fields of the training step's config the adapter registry reads (`train`, `adapter` and the
    form's section). Not `TrainStepConfig` itself: importing the training step loads Prefect and DuckDB,
    which the GPU machine lacks; the form's own config validation (AdaLoRA's schedule) still runs."""


class Form:
    """One fine-tuning form: its step configs, and whole `train` calls from the shared base weights."""

    def __init__(self, name: str, args, dataset: DemoDataset, device: torch.device, work: Path, base: dict):
        self.name, self.settings, self.args = name, FORMS[name], args
        self.dataset, self.device, self.work, self.base = dataset, device, work, base
        self.spec = policy_spec(args)
        self.base_params = sum(p.numel() for p in build_policy(self.spec, "cpu").parameters())  # no buffers
        self.runs = 0

    def step_config(self, steps: int, **kw) -> StepConfig:
        """The training step's config of a run on the device (the adapter's own check runs on it)."""
        train_config = dict(
            steps=steps,
            batch_size=self.args.batch_size,
            warmup_steps=max(1, steps // 10),
            checkpoint_every=self.args.checkpoint_every,
            log_every=10,
            device=str(self.device),
            num_threads=self.args.device_threads,
        )
        cfg = StepConfig(train=TrainConfig(**{**train_config, **kw}), **self.settings)
        ADAPTERS[cfg.adapter].check(cfg)
        return cfg

    def adapted(self, cfg: StepConfig) -> tuple[torch.nn.Module, dict, Any]:
        """The model as the training step makes it: seeded with the run's seed, base weights on the
        device, the form applied; with the form's extra losses and after-step hook."""
        form = ADAPTERS[cfg.adapter]
        torch.manual_seed(cfg.train.seed)  # the step seeds here too: adapter initialisation follows
        model = build_policy(self.spec, str(self.device))
        model.load_state_dict(self.base)
        form.apply(model, cfg)
        return model, form.extra_losses(), form.after_optimizer_step(model)

    def run_dir(self, label: str) -> Path:
        self.runs += 1
        return self.work / f"{self.name.replace(' ', '-')}-{self.runs:03d}-{label}"

    def run(self, cfg: StepConfig, label: str, run_dir: Path | None = None, **kw) -> dict:
        """A whole `train` call: its seconds, result, final weights, trainable parameters and ranks."""
        model, extra, hook = self.adapted(cfg)
        trainable = trainable_parameter_count(model)
        run_dir = run_dir or self.run_dir(label)

        def call():
            return train(
                model, self.dataset, cfg.train, run_dir, extra_losses=extra, after_optimizer_step=hook, **kw
            )

        seconds, result = timed(call, self.device)
        ranks = adalora.ranks(model) if cfg.adapter == "adalora" else None
        return {
            "seconds": seconds,
            "result": result,
            "weights": cpu_state(model),
            "trainable": trainable,
            "base": self.base_params,
            "ranks": ranks,
        }


def throughput(forms: dict[str, Form], args) -> dict[str, dict]:
    """Phase 1: per form, a warm-up call, then `rounds` timed calls of `steps` steps (order alternating)."""
    for form in forms.values():  # untimed: lazy imports, CUDA context, kernel loading, peft's first calls
        form.run(form.step_config(args.warmup_steps), "warm-up")
    runs: dict[str, list[dict]] = {name: [] for name in forms}
    names = list(forms)
    for r in range(args.rounds):
        for name in names if r % 2 == 0 else names[::-1]:
            form = forms[name]
            runs[name].append(form.run(form.step_config(args.steps), "timed"))
    out = {}
    for name, done in runs.items():
        steps = args.steps * len(done)
        out[name] = {
            "steps": steps,
            "loop_steps_per_s": round(steps / sum(args.steps / d["result"].steps_per_s for d in done), 2),
            "call_steps_per_s": round(steps / sum(d["seconds"] for d in done), 2),
            "loop_steps_per_s_rounds": [round(d["result"].steps_per_s, 2) for d in done],
            "trainable_params": done[0]["trainable"],
            "base_params": done[0]["base"],
            "final_loss": done[-1]["result"].final_loss,
            "mean_rank": statistics.mean(done[-1]["ranks"].values()) if done[-1]["ranks"] else None,
        }
    full = out["full"]
    for row in out.values():
        for kind in ("loop", "call"):
            row[f"{kind}_vs_full"] = round(row[f"{kind}_steps_per_s"] / full[f"{kind}_steps_per_s"], 3)
    return out


def resume(form: Form, args) -> dict:
    """Phase 2: interrupted after the checkpoint at half the steps and resumed, vs uninterrupted runs."""
    steps = args.resume_steps
    at = steps // 2
    cfg = form.step_config(steps, checkpoint_every=at, seed=7)
    straight = form.run(cfg, "straight")
    again = form.run(cfg, "straight-again")

    def interrupt(step: int, folder: Path) -> None:
        if step == at:
            raise Interrupted(f"interrupted after the checkpoint at step {step}")

    run_dir = form.run_dir("interrupted")
    try:
        form.run(cfg, "interrupted", run_dir, on_checkpoint=interrupt)
        raise RuntimeError("the run was not interrupted")
    except Interrupted:
        pass
    resumed = form.run(cfg, "resumed", run_dir)
    out = {
        "steps": steps,
        "interrupted_after": at,
        "resumed_from_step": resumed["result"].resumed_from_step,
        "resumed_vs_straight": difference(resumed["weights"], straight["weights"]),
        "straight_vs_straight": difference(again["weights"], straight["weights"]),
        "ranks_equal": None,
    }
    if straight["ranks"] is not None:  # AdaLoRA: the allocation the resumed run ended with
        out["ranks_equal"] = resumed["ranks"] == straight["ranks"]
        out["mean_rank"] = statistics.mean(straight["ranks"].values())
    return out


def throughput_row(name: str, row: dict) -> str:
    share = row["trainable_params"] / row["base_params"]
    rank = f"{row['mean_rank']:.2f}" if row["mean_rank"] is not None else "–"
    return (
        f"| {name} | {row['trainable_params']:,} ({share:.1%}) | {row['loop_steps_per_s']:.1f} "
        f"(call {row['call_steps_per_s']:.1f}) | {row['loop_vs_full']:.2f} "
        f"(call {row['call_vs_full']:.2f}) | "
        f"{', '.join(f'{x:.1f}' for x in row['loop_steps_per_s_rounds'])} | {rank} |\n"
    )


def resume_row(name: str, e: dict) -> str:
    ranks = {None: "–", True: "equal", False: "DIFFER"}[e["ranks_equal"]]
    return (
        f"| {name} | {e['steps']} | {e['interrupted_after']} | {e['resumed_from_step']} | "
        f"{compared(e['resumed_vs_straight'])} | {compared(e['straight_vs_straight'])} | {ranks} |\n"
    )


def markdown(entry: dict) -> str:
    env, args = entry["environment"], entry["args"]

    def rows(row: Callable[[str, dict], str], table: dict) -> str:
        return "".join(row(name, e) for name, e in table.items())

    return (
        "# Fine-tuning forms on a GPU (full, LoRA, LoRA-SP, AdaLoRA)\n\n"
        f"{entry['date']}: {env['device']} ({env['device_name']}), torch {env['torch']}, CUDA "
        f"{env['cuda_version']}, Python {entry['python']}, {args['device_threads']} torch CPU thread(s)\n"
        f"beside the device. Model: l1_chunk, state, d={args['d_model']}, 4 layers, K=8, batch "
        f"{args['batch_size']}; synthetic state demos ({entry['dataset_steps']} steps). Each form\n"
        "applied as the training step applies it (`ADAPTERS[name].apply`, its `extra_losses()`, its "
        "`after_optimizer_step` hook),\nadapters on `attn.*_proj`, `mlp.fc*`, `action_head.*` (the studies' "
        f"targets). `benchmarks/bench_adapters_cuda.py`, {entry['seconds']:.0f} s in all.\n\n"
        "## 1. Steps/s per form\n\n"
        "Steps/s of the training loop (`TrainResult.steps_per_s`), and of the whole `train` call (set-up,\n"
        f"checkpoints every {args['checkpoint_every']} steps and the final save included); {args['rounds']} "
        f"round(s) of {args['steps']} steps per form,\nthe order of the forms reversed every other round. "
        "vs full: the form's steps/s over full fine-tuning's in this run.\n"
        "Trainable params: in brackets, their share of the base model's parameters. Mean rank: AdaLoRA's\n"
        "average kept rank per layer at the end of the run (its target_r is 8).\n\n"
        "| form | trainable params | steps/s | vs full | loop steps/s per round | mean rank |\n"
        "|---|---|---|---|---|---|\n" + rows(throughput_row, entry["throughput"]) + "\n"
        "## 2. Exact resume on the device\n\n"
        "A run whose `on_checkpoint` raises after the checkpoint at half its steps, then resumed in the\n"
        "same run dir, against an uninterrupted run; two uninterrupted runs against each other give the\n"
        "floor set by non-deterministic kernels. Max diff: the largest absolute difference of any weight\n"
        "(adapter tensors included). Ranks: AdaLoRA's final allocation, resumed vs uninterrupted.\n\n"
        "| form | steps | interrupted after | resumed from | resumed vs straight | straight vs straight "
        "| ranks |\n|---|---|---|---|---|---|---|\n" + rows(resume_row, entry["resume"])
    )


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_device_options(ap, "adapters_cuda")
    ap.add_argument("--steps", type=int, default=100, help="steps per timed call (per form and round)")
    ap.add_argument("--rounds", type=int, default=2, help="timed calls per form, order alternating")
    ap.add_argument("--resume-steps", type=int, default=100, help="steps of the resume check's runs")
    ap.add_argument("--warmup-steps", type=int, default=5, help="steps of each form's untimed first call")
    ap.add_argument("--write", action="store_true", help="write the results of a --quick run too")
    args = ap.parse_args()
    if args.quick:
        args.steps, args.rounds, args.resume_steps, args.warmup_steps, args.d_model = 10, 1, 10, 5, 32
        args.device_threads = 1  # a shared CPU crawls with more
    return args


def measure(args, device: torch.device, dataset: DemoDataset, work: Path) -> tuple[dict, dict]:
    torch.manual_seed(0)
    base = build_policy(policy_spec(args), "cpu").state_dict()  # the weights every form starts from
    forms = {name: Form(name, args, dataset, device, work, base) for name in FORMS}
    speed = throughput(forms, args)
    for name, row in speed.items():
        say(
            f"[1/2 throughput] {name}: {row['loop_steps_per_s']:.1f} steps/s "
            f"(call {row['call_steps_per_s']:.1f}), x{row['loop_vs_full']:.2f} of full; "
            f"{row['trainable_params']:,} trainable"
        )
    exact = {}
    for name in RESUMED:
        exact[name] = e = resume(forms[name], args)
        say(
            f"[2/2 resume] {name}: resumed from step {e['resumed_from_step']}; resumed vs straight "
            f"{compared(e['resumed_vs_straight'])}; straight vs straight "
            f"{compared(e['straight_vs_straight'])}; ranks equal: {e['ranks_equal']}"
        )
    return speed, exact


def main() -> None:
    started = time.perf_counter()
    args = parse_args()
    device = resolve_device(args.device)
    env = run_environment(device)
    say(f"[0/2] {env['device']} ({env['device_name']}), torch {env['torch']}, CUDA {env['cuda_version']}")
    dataset = make_dataset()
    work = Path(tempfile.mkdtemp(prefix="bench-adapters-cuda-"))
    try:
        speed, exact = measure(args, device, dataset, work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    entry = entry_of(started, env, dataset, args, throughput=speed, resume=exact)
    print(json.dumps(entry, indent=1))
    if args.quick and not args.write:
        say(f"dry run: nothing written ({entry['seconds']:.0f} s in all; --write writes it)")
        return
    write_results(args.results, "adapters_cuda", entry, markdown(entry))


if __name__ == "__main__":
    main()
