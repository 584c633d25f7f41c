#!/usr/bin/env bash
# Reproduces the comparison reports with the pipeline itself. Every step is cached, so re-running
# costs only what changed. Budgets for the ablations are cut to fit one working session on a 2-core
# machine (see the comments).
#   quick  -> docs/results.md         state + `dynamics`, easy downstream tasks (about an hour)
#   hard   -> docs/results_hard.md    state + `dynamics`, grasp/insertion downstream tasks (~40 min)
#             docs/results_hard_adapters.md  every arm at a validation-chosen lr, with LoRA and LoRA-SP
#             arms (~2 hours more)
#   pixels -> docs/results_pixels.md  camera + `spatial`, the `paper` setting cut to CPU (~1 hour)
# Usage: scripts/reproduce_results.sh [quick|hard|pixels|all]   (CAPVECTOR_HOME defaults to ./capvector_home)
set -euo pipefail
cd "$(dirname "$0")/.."
cv=".venv/bin/capvector"
ids() { .venv/bin/python -c 'import json,sys; print(json.load(sys.stdin)[sys.argv[1]])' "$1"; }

# α and λ on validation goal variations (never the test seeds); sets $sweep, $alpha, $lambda, $chosen.
sweep_for() {
  read -r sweep alpha lambda < <($cv sweep --preset "$1" --json | .venv/bin/python -c \
    'import json,sys; d=json.load(sys.stdin); print(d["sweep"], d["best"]["alpha"], d["best"]["lambda"])')
  echo "sweep $sweep ($1) chose alpha=$alpha lambda=$lambda"
  chosen=(--set "alpha=$alpha" --set "orthogonal.weight=$lambda")
}

quick() {
  # Let a run started earlier finish first (two runs would compute the same steps twice).
  while pgrep -f "capvector (run|sweep) --preset quick" >/dev/null; do sleep 5; done
  sweep_for quick
  # The comparison: sft, aux, capvector, meta_sft (CapVector without the orthogonal loss), 3 seeds.
  main=$($cv run --preset quick "${chosen[@]}" --json | ids report)
  # Convergence: the main arms at smaller downstream budgets (the schedule shape is the same).
  half=$($cv run --preset quick "${chosen[@]}" --set 'arms=[sft, aux, capvector]' --set downstream.steps=400 \
    --set downstream.checkpoint_every=200 --json | ids report)
  b200=$($cv run --preset quick "${chosen[@]}" --set 'arms=[sft, aux, capvector]' --set downstream.steps=200 \
    --set downstream.warmup_steps=20 --set downstream.checkpoint_every=100 --json | ids report)
  b100=$($cv run --preset quick "${chosen[@]}" --set 'arms=[sft, aux, capvector]' --set downstream.steps=100 \
    --set downstream.warmup_steps=10 --set downstream.checkpoint_every=100 --json | ids report)
  # LoRA versions of (i) and (iii), seed 0 (CPU budget).
  lora=$($cv run --preset quick "${chosen[@]}" --set 'arms=[sft_lora, capvector_lora]' --set 'seeds=[0]' --json \
    | ids report)
  # γ masked to parts of the network (seed 0).
  attn=$($cv run --preset quick "${chosen[@]}" --set 'arms=[capvector]' --set 'seeds=[0]' \
    --set 'vector.include=["backbone.layers.*.attn.*"]' --json | ids report)
  mlp=$($cv run --preset quick "${chosen[@]}" --set 'arms=[capvector]' --set 'seeds=[0]' \
    --set 'vector.include=["backbone.layers.*.mlp.*"]' --json | ids report)
  # LoRA-SP versions of (i) and (iii): seed 0, 400 steps, bank 16 (about 5x slower per step than LoRA on CPU).
  lorasp=$($cv run --preset quick "${chosen[@]}" --set 'arms=[sft_lora_sp, capvector_lora_sp]' --set 'seeds=[0]' \
    --set downstream.steps=400 --set downstream.checkpoint_every=200 --set lora_sp.bank_size=16 --json | ids report)

  $cv report "$main" -o docs/results.md --sweep "$sweep" --notes docs/results_notes.md \
    --section "Half the downstream budget (400 steps)=$half" \
    --section "200 downstream steps=$b200" \
    --section "100 downstream steps=$b100" \
    --section "LoRA (r=8) on attention, MLP and action head, seed 0=$lora" \
    --section "LoRA-SP (bank 16, η=0.9), 400 steps, seed 0=$lorasp" \
    --section "γ masked to attention projections, seed 0=$attn" \
    --section "γ masked to MLPs, seed 0=$mlp"
}

hard() {
  sweep_for hard
  main=$($cv run --preset hard "${chosen[@]}" --json | ids report)
  half=$($cv run --preset hard "${chosen[@]}" --set 'arms=[sft, aux, capvector]' --set downstream.steps=400 \
    --set downstream.checkpoint_every=200 --json | ids report)
  # γ masked to parts of the network (seed 0).
  attn=$($cv run --preset hard "${chosen[@]}" --set 'arms=[capvector]' --set 'seeds=[0]' \
    --set 'vector.include=["backbone.layers.*.attn.*"]' --json | ids report)
  mlp=$($cv run --preset hard "${chosen[@]}" --set 'arms=[capvector]' --set 'seeds=[0]' \
    --set 'vector.include=["backbone.layers.*.mlp.*"]' --json | ids report)
  $cv report "$main" -o docs/results_hard.md --sweep "$sweep" --notes docs/results_hard_notes.md \
    --section "Half the downstream budget (400 steps)=$half" \
    --section "γ masked to attention projections, seed 0=$attn" \
    --section "γ masked to MLPs, seed 0=$mlp"
}

# The best learning rate of one arm on validation goals (one-cell sweeps, seed 0): sets $best_lr and
# appends each cell's sweep id to $cells. Usage: best_lr ARM LR_KEY LR... (extra --set from $chosen).
best_lr() {
  local arm=$1 key=$2 lr cell score best=-1
  shift 2
  for lr in "$@"; do
    read -r cell score < <($cv sweep --preset hard "${chosen[@]}" --set lora_sp.bank_size=16 --set sweep.arm="$arm" \
      --set "sweep.alphas=[$alpha]" --set "sweep.lambdas=[$lambda]" --set "$key=$lr" --json | .venv/bin/python -c \
      'import json,sys; d=json.load(sys.stdin); print(d["sweep"], d["best"]["validation_success"])')
    cells+=(--sweep "$cell")
    if .venv/bin/python -c "import sys; sys.exit(not $score > $best)"; then best=$score best_lr=$lr; fi
  done
  echo "$arm: $key=$best_lr (validation success $best)"
}

# LoRA (r=8) and LoRA-SP (bank 16) versions of (i) and (iii) beside the full fine-tuning arms, 3 seeds,
# in two passes. First the adapter lr is chosen on the SFT-LoRA arm and every arm runs with the
# preset's full fine-tuning lr and the first sweep's α, λ ("untuned"). Then the full fine-tuning lr is
# chosen on the SFT arm, α and λ are re-swept at that lr, and every arm runs again ("tuned").
hard_tuned() {
  local cells=() arms full_lr adapter_lr untuned tuned
  arms='arms=[sft, aux, capvector, meta_sft, sft_lora, capvector_lora, sft_lora_sp, capvector_lora_sp]'
  sweep_for hard
  best_lr sft_lora adapter_lr 1e-4 1e-3 3e-3 1e-2
  adapter_lr=$best_lr
  untuned=$($cv run --preset hard "${chosen[@]}" --set lora_sp.bank_size=16 --set adapter_lr="$adapter_lr" \
    --set "$arms" --json | ids report)
  best_lr sft downstream.lr 1e-4 3e-4 1e-3 3e-3
  full_lr=$best_lr
  read -r sweep alpha lambda < <($cv sweep --preset hard --set downstream.lr="$full_lr" --json | .venv/bin/python -c \
    'import json,sys; d=json.load(sys.stdin); print(d["sweep"], d["best"]["alpha"], d["best"]["lambda"])')
  echo "sweep $sweep (lr $full_lr) chose alpha=$alpha lambda=$lambda"
  chosen=(--set "alpha=$alpha" --set "orthogonal.weight=$lambda")
  tuned=$($cv run --preset hard "${chosen[@]}" --set lora_sp.bank_size=16 --set downstream.lr="$full_lr" \
    --set adapter_lr="$adapter_lr" --set "$arms" --json | ids report)
  $cv report "$tuned" -o docs/results_hard_adapters.md --notes docs/results_hard_adapters_notes.md \
    --section "Untuned: full fine-tuning at the preset lr, α and λ of the first sweep=$untuned" \
    --sweep "$sweep" "${cells[@]}"
}

pixels() {
  sweep_for paper-cpu
  # The pipeline also tests every final checkpoint through evaluation.ood_camera (corner3).
  out=$($cv run --preset paper-cpu "${chosen[@]}" --json)
  main=$(ids report <<<"$out")
  ood=$(ids ood_report <<<"$out")
  $cv report "$main" -o docs/results_pixels.md --sweep "$sweep" --notes docs/results_pixels_notes.md \
    --section "Out of distribution: the same checkpoints seen through another camera (corner3)=$ood"
}

case "${1:-all}" in
  quick) quick ;;
  hard) hard; hard_tuned ;;
  pixels) pixels ;;
  all) quick; hard; hard_tuned; pixels ;;
  *) echo "usage: $0 [quick|hard|pixels|all]" >&2; exit 2 ;;
esac
