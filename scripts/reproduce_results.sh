#!/usr/bin/env bash
# Reproduces docs/results.md with the pipeline itself (quick preset, state observations, `dynamics`).
# Every step is cached, so re-running costs only what changed. Takes about an hour on 2 CPU cores.
# Budgets for the ablations are cut to fit one working session on a 2-core machine (see the comments).
# Usage: scripts/reproduce_results.sh   (CAPVECTOR_HOME defaults to ./capvector_home)
set -euo pipefail
cd "$(dirname "$0")/.."
cv=".venv/bin/capvector"
ids() { .venv/bin/python -c 'import json,sys; print(json.load(sys.stdin)[sys.argv[1]])' "$1"; }

# Let a run started earlier finish first (two runs would compute the same steps twice).
while pgrep -f "capvector (run|sweep) --preset quick" >/dev/null; do sleep 5; done

# 1. α and λ on validation goal variations (never the test seeds).
read -r sweep alpha lambda < <($cv sweep --preset quick --json | .venv/bin/python -c \
  'import json,sys; d=json.load(sys.stdin); print(d["sweep"], d["best"]["alpha"], d["best"]["lambda"])')
echo "sweep $sweep chose alpha=$alpha lambda=$lambda"
chosen=(--set "alpha=$alpha" --set "orthogonal.weight=$lambda")

# 2. The comparison: sft, aux, capvector, meta_sft (CapVector without the orthogonal loss), 3 seeds.
main=$($cv run --preset quick "${chosen[@]}" --json | ids report)
# 3. Convergence: the main arms at smaller downstream budgets (the schedule shape is the same).
half=$($cv run --preset quick "${chosen[@]}" --set 'arms=[sft, aux, capvector]' --set downstream.steps=400 \
  --set downstream.checkpoint_every=200 --json | ids report)
b200=$($cv run --preset quick "${chosen[@]}" --set 'arms=[sft, aux, capvector]' --set downstream.steps=200 \
  --set downstream.warmup_steps=20 --set downstream.checkpoint_every=100 --json | ids report)
b100=$($cv run --preset quick "${chosen[@]}" --set 'arms=[sft, aux, capvector]' --set downstream.steps=100 \
  --set downstream.warmup_steps=10 --set downstream.checkpoint_every=100 --json | ids report)
# 4. LoRA versions of (i) and (iii), seed 0 (CPU budget).
lora=$($cv run --preset quick "${chosen[@]}" --set 'arms=[sft_lora, capvector_lora]' --set 'seeds=[0]' --json | ids report)
# 5. γ masked to parts of the network (seed 0).
attn=$($cv run --preset quick "${chosen[@]}" --set 'arms=[capvector]' --set 'seeds=[0]' \
  --set 'vector.include=["backbone.layers.*.attn.*"]' --json | ids report)
mlp=$($cv run --preset quick "${chosen[@]}" --set 'arms=[capvector]' --set 'seeds=[0]' \
  --set 'vector.include=["backbone.layers.*.mlp.*"]' --json | ids report)
# 6. LoRA-SP versions of (i) and (iii): seed 0, 400 steps, bank 16 (about 5x slower per step than LoRA on CPU).
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
