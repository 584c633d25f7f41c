"""Benchmark (b): training-step cost of the orthogonal regularizer, LoRA and LoRA-SP on our policy.

Model: the `l1_chunk` policy (`L1ChunkPolicy`) in state mode, d_model 128, 4 layers, batch 64, AdamW, CPU.
Variants: full fine-tuning with and without the dense orthogonal regularizer (λ = 1e-4, γ on every
parameter tensor), LoRA (r 16 on q/k/v/o and the MLP) alone and with the A-only and exact regularizers,
and LoRA-SP (bank 128, η 0.9) with its spectral + router losses. Steps of every variant are timed in
interleaved blocks (the CPU is shared), and the median step time is reported. Target: regularizer
overhead ≤ 5% for full fine-tuning.

Usage: .venv/bin/python benchmarks/bench_adapters.py [--reps 5] [--steps 20]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from capvector.core.adapters.lora import LoraConfig, adapter_modules, apply_lora, trainable_parameter_count  # noqa: E402
from capvector.core.adapters.lora_sp import LoraSPConfig, active_ranks, apply_lora_sp, lora_sp_loss  # noqa: E402
from capvector.core.policies import L1ChunkConfig, L1ChunkPolicy  # noqa: E402
from capvector.core.training.orthogonal import OrthogonalRegularizer  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
BATCH = 64
TARGETS = ["q_proj", "k_proj", "v_proj", "o_proj", "fc1", "fc2"]


def make_batch(cfg: L1ChunkConfig, g: torch.Generator) -> dict[str, torch.Tensor]:
    return {
        "tokens": torch.randint(1, cfg.vocab_size, (BATCH, cfg.max_instruction_tokens), generator=g),
        "state": torch.randn(BATCH, cfg.state_dim, generator=g),
        "proprio": torch.randn(BATCH, cfg.proprio_dim, generator=g),
        "actions": torch.randn(BATCH, cfg.chunk_size, cfg.action_dim, generator=g),
    }


def build(variant: str, cfg: L1ChunkConfig, gamma: dict[str, torch.Tensor], meta: dict[str, torch.Tensor]):
    """A model, its optimizer and its extra losses for one variant."""
    model = L1ChunkPolicy(cfg)
    model.load_state_dict(meta)
    extra = {}
    if variant.startswith("lora_sp"):
        apply_lora_sp(model, LoraSPConfig(target_modules=TARGETS, bank_size=128, alpha=256, eta=0.9))
        extra["lora_sp"] = lora_sp_loss
    elif variant.startswith("lora"):
        apply_lora(model, LoraConfig(target_modules=TARGETS, r=16, alpha=32))
        with torch.no_grad():  # non-zero B so the exact form does real work
            for m in adapter_modules(model).values():
                m.lora_B["default"].weight.normal_(std=1e-3)
    if variant == "full+orth":
        extra["orth"] = OrthogonalRegularizer(model, gamma, meta, lambda_absolute=1e-4)
    elif variant == "lora+orth_a":
        extra["orth"] = OrthogonalRegularizer(model, gamma, lambda_absolute=1e-4, mode="lora_a")
    elif variant == "lora+orth_exact":
        extra["orth"] = OrthogonalRegularizer(model, gamma, lambda_absolute=1e-4, mode="lora_exact")
    opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-4)
    return model, opt, extra


def step(model, opt, extra, batch) -> None:
    opt.zero_grad(set_to_none=True)
    loss = model.compute_loss(batch).loss
    for fn in extra.values():
        loss = loss + fn(model)
    loss.backward()
    opt.step()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--steps", type=int, default=20)
    args = ap.parse_args()
    load_before = os.getloadavg()[0]
    torch.manual_seed(0)
    torch.set_num_threads(2)
    cfg = L1ChunkConfig(obs_mode="state", d_model=128, n_layers=4)
    meta = {k: v.clone() for k, v in L1ChunkPolicy(cfg).state_dict().items()}
    gamma = {k: 1e-3 * torch.randn_like(v) for k, v in meta.items() if v.is_floating_point()}
    variants = ["full", "full+orth", "lora", "lora+orth_a", "lora+orth_exact", "lora_sp"]
    g = torch.Generator().manual_seed(0)
    batches = [make_batch(cfg, g) for _ in range(4)]
    built = {v: build(v, cfg, gamma, meta) for v in variants}
    for model, opt, extra in built.values():  # warm-up
        for b in batches:
            step(model, opt, extra, b)
    times: dict[str, list[float]] = {v: [] for v in variants}
    for rep in range(args.reps):
        for v in variants if rep % 2 == 0 else variants[::-1]:
            model, opt, extra = built[v]
            t = time.perf_counter()
            for i in range(args.steps):
                step(model, opt, extra, batches[i % len(batches)])
            times[v].append((time.perf_counter() - t) / args.steps * 1e3)
    rows = {}
    for v in variants:
        model, _, _ = built[v]
        ranks = active_ranks(model)
        rows[v] = {
            "step_ms_min": min(times[v]),
            "step_ms_median": statistics.median(times[v]),
            "step_ms_blocks": times[v],
            "trainable_params": trainable_parameter_count(model),
            "mean_active_rank": statistics.mean(ranks.values()) if ranks else None,
        }
        print(v, rows[v], flush=True)
    full, orth = rows["full"]["step_ms_min"], rows["full+orth"]["step_ms_min"]
    lora = rows["lora"]["step_ms_min"]
    model, _, extra = built["full+orth"]
    reg_ms = []
    for _ in range(5):  # the regularizer alone (forward + backward), less exposed to load spikes
        t = time.perf_counter()
        for _ in range(20):
            extra["orth"](model).backward()
        reg_ms.append((time.perf_counter() - t) / 20 * 1e3)
    result = {
        "model": "l1_chunk policy, state mode, d_model 128, 4 layers, batch 64, AdamW, 2 CPU threads",
        "steps_per_block": args.steps,
        "blocks": args.reps,
        "rows": rows,
        "orth_overhead_full": orth / full - 1,
        "orth_alone_ms": min(reg_ms),
        "orth_alone_share_of_full_step": min(reg_ms) / full,
        "orth_a_overhead_lora": rows["lora+orth_a"]["step_ms_min"] / lora - 1,
        "orth_exact_overhead_lora": rows["lora+orth_exact"]["step_ms_min"] / lora - 1,
        "lora_sp_layer_ranks": active_ranks(built["lora_sp"][0]),
        "target_full_overhead_le_5pct": orth / full - 1 <= 0.05,
        "load_average_1min": [load_before, os.getloadavg()[0]],
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "adapters.json").write_text(json.dumps(result, indent=2))
    lines = [
        "# Adapter and regularizer step-time benchmark (bench_adapters.py)",
        "",
        f"{result['model']}; fastest (and median) of {args.reps} interleaved blocks of {args.steps} steps. "
        f"1-minute load average before/after: {load_before:.1f} / {result['load_average_1min'][1]:.1f} "
        "(2 cores shared with other work: step times scale with it, compare rows of one run only).",
        "",
        "| variant | step ms (min) | step ms (median) | trainable params | mean active rank |",
        "|---|---|---|---|---|",
    ]
    for v, r in rows.items():
        rank = f"{r['mean_active_rank']:.1f} / 128" if r["mean_active_rank"] is not None else "–"
        lines.append(
            f"| {v} | {r['step_ms_min']:.2f} | {r['step_ms_median']:.2f} | "
            f"{r['trainable_params']:,} | {rank} |"
        )
    lines += [
        "",
        "- orthogonal regularizer overhead, full fine-tuning: "
        f"**{100 * result['orth_overhead_full']:+.1f}%** "
        f"(target ≤ 5%: {'met' if result['target_full_overhead_le_5pct'] else 'NOT met'}); the regularizer "
        f"alone (forward + backward, {len(extra['orth'].names)} tensors) costs "
        f"{result['orth_alone_ms']:.2f} ms = "
        f"{100 * result['orth_alone_share_of_full_step']:.1f}% of the fastest full step",
        f"- LoRA + A-only regularizer: {100 * result['orth_a_overhead_lora']:+.1f}%; LoRA + exact (B·A) "
        f"regularizer: {100 * result['orth_exact_overhead_lora']:+.1f}%",
        "- LoRA-SP active ranks (training EMA, η = 0.9, after warm-up + timed steps only, untrained): "
        + ", ".join(
            f"{k.replace('backbone.layers.', 'L')}: {v:.0f}" for k, v in result["lora_sp_layer_ranks"].items()
        ),
    ]
    (RESULTS / "adapters.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
