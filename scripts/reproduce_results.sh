#!/usr/bin/env bash
# Reproduces the study reports in docs/studies/ with the `study` flow: every choice (lr, auxiliary weights, α,
# λ) is made inside the flow on validation goals and recorded as a `selection` artifact; each report is
# written with its figures beside it. Every step is cached, so a study interrupted in one session goes on
# where it stopped in the next.
#   control-small -> docs/studies/study_control_small.md  the random-feature positive-control testbed, 2 x 2
#   control       -> docs/studies/study_control.md        the same testbed, 2 draws x 2 seeds x 140 test goals
#   control-10000 -> docs/studies/study_control_10000.md  the same at its declared 3 x 3, extraction 10,000 steps
#   control-hard  -> docs/studies/study_control_hard.md   the six hardest calibrated tasks downstream
#   control-flow  -> docs/studies/study_control_flow.md   `control` on the flow-matching backbone
#   control-2demos -> docs/studies/study_control_small_2demos.md  `control-small` with 2 downstream demos per task
#   control-large  -> docs/studies/study_control_small_large.md   `control-small` with d_model 128 x 4 layers
#   control-large-3draws -> docs/studies/study_control_small_large_3draws.md  the same with a third γ draw
#   control-large-5draws -> docs/studies/study_control_small_large_5draws.md  the same with five γ draws
#   control-large-2000 -> docs/studies/study_control_small_large_2000.md  3 draws, 2000-step extraction runs
#   control-hard-extraction-split -> docs/studies/study_control_small_hard_extraction.md  `control-small` with the six
#                      hardest calibrated tasks for extraction (room for precondition b), the nine others downstream
#   control-hard-extraction-small -> docs/studies/study_control_hard_extraction_small.md  `make run` until issue 41:
#                      the same split with the larger policy (d_model 128 x 4 layers) and 3 γ draws
#   control-hard-extraction-3seeds -> docs/studies/study_control_hard_extraction_3seeds.md  the default of `make run`
#                      since issue 41: the same with 3 training seeds and 2 tuning seeds
#   control-hard-extraction-large-5draws -> docs/studies/study_control_small_hard_extraction_large_5draws.md  the
#                      same with 5 γ draws and 20 test goals per task (the size its report asks for)
#   control-hard-extraction -> docs/studies/study_control_hard_extraction.md  the study that answers the question:
#                      3 γ draws, 8 training seeds, 30 test goals per task (the 5-draw report's sizing)
#   control-hard-extraction-small-flow -> docs/studies/study_control_hard_extraction_small_flow.md  `make run`'s
#                      study on the flow-matching backbone (policy.type=flow; declared after the l1_chunk result,
#                      at make-run size because the 8-seed design takes longer than a session has left)
#   control-hard-extraction-flow -> docs/studies/study_control_hard_extraction_flow.md  the 8-seed study on the flow
#                      backbone (declared after the make-run-size flow study: aux - SFT +9.8 on df 1, (c) +8.5)
#   conclusive    -> docs/studies/study_conclusive.md     issue 39's declared study (declared_conclusive.md), run from
#                    its pinned revision d117758 in a temporary worktree (the code its report was made with)
#   conclusive-gate -> docs/studies/study_conclusive_gate.md  issue 39's powered gate (declared_conclusive_gate.md),
#                    from its pinned revision 3f77d4d, the code it has run with since 2026-12-08 (its
#                    steps' caches are found only with that code; it computes its own pretraining, demos and draws)
#   state         -> docs/studies/study_state.md          the earlier state testbed (no positive control)
#   pixels        -> docs/studies/study_pixels.md         camera images, per-patch depth targets (GPU-sized; the
#                    pixels gate actually run on a lent GPU is docs/studies/study_pixels_gpu.md, scripts/pixels_gate_gpu.py)
# Usage: scripts/reproduce_results.sh [control-small|control|control-10000|control-hard|control-flow|
#        control-2demos|control-large|control-large-3draws|control-large-5draws|control-large-2000|
#        control-hard-extraction|control-hard-extraction-small|control-hard-extraction-3seeds|
#        control-hard-extraction-large-5draws|control-hard-extraction-split|control-hard-extraction-small-flow|control-hard-extraction-flow|
#        conclusive|conclusive-gate|state|pixels]   (CAPVECTOR_HOME: ./capvector_home)
# The calibration behind the control presets: docs/studies/calibration.md (capvector calibrate --preset
# calibrate-control, scripts/pilot_aux.py).
set -euo pipefail
cd "$(dirname "$0")/.."
preset="${1:-control-hard-extraction-3seeds}"
case "$preset" in
  control-small | control | control-hard | control-hard-extraction | control-hard-extraction-small | \
  control-hard-extraction-3seeds | state | pixels)
    .venv/bin/capvector study --preset "study-$preset" --report "docs/studies/study_${preset//-/_}.md" ;;
  control-10000)
    .venv/bin/capvector study --preset study-control --set 'study.draws=[0,1,2]' --set 'seeds=[0,1,2]' \
      --set extraction.steps=10000 --set extraction.checkpoint_every=2500 --report docs/studies/study_control_10000.md ;;
  control-flow)
    .venv/bin/capvector study --preset study-control --set policy.type=flow --report docs/studies/study_control_flow.md ;;
  control-2demos)
    .venv/bin/capvector study --preset study-control-small --set data.episodes_downstream=2 \
      --report docs/studies/study_control_small_2demos.md ;;
  control-large | control-large-3draws | control-large-5draws)
    case "$preset" in
      control-large) draws="[0,1]" report=docs/studies/study_control_small_large.md ;;
      control-large-3draws) draws="[0,1,2]" report=docs/studies/study_control_small_large_3draws.md ;;
      *) draws="[0,1,2,3,4]" report=docs/studies/study_control_small_large_5draws.md ;;
    esac
    .venv/bin/capvector study --preset study-control-small --set name=study-control-small-large \
      --set policy.d_model=128 --set policy.n_layers=4 --set "study.draws=$draws" --report "$report" ;;
  control-large-2000)
    .venv/bin/capvector study --preset study-control-small --set name=study-control-small-large \
      --set policy.d_model=128 --set policy.n_layers=4 --set "study.draws=[0,1,2]" \
      --set extraction.steps=2000 --set extraction.checkpoint_every=500 \
      --report docs/studies/study_control_small_large_2000.md ;;
  control-hard-extraction-split)
    .venv/bin/capvector study --preset study-control-small --set name=study-control-small-hard-extraction \
      --set 'splits.extraction=[dial-turn-v3,door-unlock-v3,door-lock-v3,door-close-v3,plate-slide-back-v3,window-close-v3]' \
      --set 'splits.downstream=[faucet-close-v3,handle-press-side-v3,coffee-button-v3,button-press-v3,button-press-wall-v3,faucet-open-v3,handle-press-v3,drawer-close-v3,plate-slide-side-v3]' \
      --report docs/studies/study_control_small_hard_extraction.md ;;
  control-hard-extraction-large-5draws)
    .venv/bin/capvector study --preset study-control-small --set name=study-control-small-hard-extraction-large \
      --set 'splits.extraction=[dial-turn-v3,door-unlock-v3,door-lock-v3,door-close-v3,plate-slide-back-v3,window-close-v3]' \
      --set 'splits.downstream=[faucet-close-v3,handle-press-side-v3,coffee-button-v3,button-press-v3,button-press-wall-v3,faucet-open-v3,handle-press-v3,drawer-close-v3,plate-slide-side-v3]' \
      --set policy.d_model=128 --set policy.n_layers=4 --set 'study.draws=[0,1,2,3,4]' \
      --set evaluation.episodes_per_task=20 --report docs/studies/study_control_small_hard_extraction_large_5draws.md ;;
  control-hard-extraction-small-flow)
    .venv/bin/capvector study --preset study-control-hard-extraction-small --set policy.type=flow \
      --set name=study-control-hard-extraction-small-flow --report docs/studies/study_control_hard_extraction_small_flow.md ;;
  control-hard-extraction-flow)
    .venv/bin/capvector study --preset study-control-hard-extraction --set policy.type=flow \
      --set name=study-control-hard-extraction-flow --report docs/studies/study_control_hard_extraction_flow.md ;;
  conclusive | conclusive-gate)
    # the pinned revision's own code (capvector/__init__.py maps the package onto the worktree's folders)
    if [ "$preset" = conclusive ]; then rev=d117758; else rev=3f77d4d; fi
    tree="$(mktemp -d)/src"
    git worktree add --detach "$tree" "$rev"
    trap 'git worktree remove --force "$tree"' EXIT
    PYTHONPATH="$tree" .venv/bin/capvector study --preset "study-$preset" --report "docs/studies/study_${preset//-/_}.md" ;;
  *) echo "usage: $0 [control-small|control|control-10000|control-hard|control-flow|control-2demos|control-large|control-large-3draws|control-large-5draws|control-large-2000|control-hard-extraction|control-hard-extraction-small|control-hard-extraction-large-5draws|control-hard-extraction-split|control-hard-extraction-small-flow|control-hard-extraction-flow|conclusive|conclusive-gate|state|pixels]" >&2
     exit 2 ;;
esac
