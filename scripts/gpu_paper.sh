#!/usr/bin/env bash
# The paper-protocol tables (experiments/paper.py) on one GPU machine, the arms split over
# several processes that run at once (each process is one run folder; experiments/paper_merge.py
# merges the folders into one table; docs/experiments.md, "How the tables were made").
# Usage, from the repository root with the project importable (docs/gpu.md):
#   scripts/gpu_paper.sh OUT_DIR PRESET 'ARMS ...' 'ARMS ...' ...  [-- extra flags for every run]
# e.g. scripts/gpu_paper.sh runs/gpu catching_paper 'plain frozen fixed_energy fixed_speed' online
# Each group runs as experiments/paper.py --preset PRESET --arms ARMS --out OUT_DIR/PRESET-<i>,
# its log beside it; every process is stopped after ${TIMEOUT_S:-570} s.
set -uo pipefail
out=${1:?usage: scripts/gpu_paper.sh OUT_DIR PRESET GROUP... [-- flags]}
preset=${2:?preset}
shift 2
groups=()
while (($#)) && [[ $1 != -- ]]; do groups+=("$1"); shift; done
[[ ${1:-} == -- ]] && shift
mkdir -p "$out"
export XLA_PYTHON_CLIENT_PREALLOCATE=false PYTHONUNBUFFERED=1
# Reproducible GPU numerics (unless XLA_FLAGS is set): with XLA's defaults two runs of the same
# code on one H200 gave round-off-level differences (7e-11) in catching, but learned networks
# that hit differently in hitting (every held-out run's largest pulse moved, by up to 101 N);
# with deterministic ops three runs were identical (docs/experiments.md, session 67). An
# XLA_FLAGS given in the environment replaces this (add the flag to it to keep it).
export XLA_FLAGS=${XLA_FLAGS:---xla_gpu_deterministic_ops=true}
py=${PYTHON:-python3}
i=0
for g in "${groups[@]}"; do
  # shellcheck disable=SC2086  # a group is a space-separated list of arms
  timeout "${TIMEOUT_S:-570}" "$py" experiments/paper.py --preset "$preset" --arms $g \
    --out "$out/$preset-$i" "$@" > "$out/$preset-$i.log" 2>&1 &
  i=$((i + 1))
done
wait
