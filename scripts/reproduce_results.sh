#!/usr/bin/env bash
# Reproduces the study reports in docs/ with the `study` flow: every choice (lr, auxiliary weight, α, λ)
# is made inside the flow on validation goals and recorded as a `selection` artifact. Every step is
# cached, so a study interrupted in one session goes on where it stopped in the next.
#   small  -> docs/study_small.md   the default of `make run` (about 20 minutes on 2 cores cold)
#   state  -> docs/study_state.md   state observations, 252 test goals per checkpoint
#   pixels -> docs/study_pixels.md  camera images, per-patch depth targets (GPU-sized; runs on CPU slowly)
# Usage: scripts/reproduce_results.sh [small|state|pixels|all]   (CAPVECTOR_HOME defaults to ./capvector_home)
# The earlier reports (docs/results*.md) came from `capvector run` and `sweep` calls of commit cc24b72's
# version of this script.
set -euo pipefail
cd "$(dirname "$0")/.."
study() { .venv/bin/capvector study --preset "study-$1" --report "docs/study_$1.md"; }
case "${1:-small}" in
  small | state | pixels) study "$1" ;;
  all) study small && study state && study pixels ;;
  *) echo "usage: $0 [small|state|pixels|all]" >&2; exit 2 ;;
esac
