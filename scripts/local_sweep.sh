#!/bin/bash
# The SLURM job array on one machine (for tests, or a host without a scheduler): N local shard
# processes in the background, each `experiments/sweep.py --shard-index i --num-shards N`, then
# the merge (--merge-only), all with the same sweep arguments. From the repository root:
#
#   scripts/local_sweep.sh 2 runs/sweep --seeds 1 --rod-lengths 0.6 0.65 ...
#
# Shard i's output goes to OUT/logs/shard_i.log. Exits with the first failing shard's exit code
# (without merging), else with the merge's. DRY_RUN=1 only prints the commands.
set -uo pipefail

if [[ $# -lt 2 || ! $1 =~ ^[1-9][0-9]*$ ]]; then
  echo "usage: $0 N_SHARDS OUT [sweep arguments ...]" >&2
  exit 2
fi
n=$1
out=$2
shift 2
py=${PYTHON:-python}
cd "$(dirname "${BASH_SOURCE[0]}")/.."

if [[ -n ${DRY_RUN:-} ]]; then
  for ((i = 0; i < n; i++)); do
    echo "$py experiments/sweep.py --out $out --shard-index $i --num-shards $n $*"
  done
  echo "$py experiments/sweep.py --out $out --merge-only $*"
  exit 0
fi

mkdir -p "$out/logs"
pids=()
for ((i = 0; i < n; i++)); do
  "$py" experiments/sweep.py --out "$out" --shard-index "$i" --num-shards "$n" "$@" \
    >"$out/logs/shard_$i.log" 2>&1 &
  pids+=($!)
done
status=0
for i in "${!pids[@]}"; do
  wait "${pids[$i]}"
  rc=$?
  if [[ $rc -ne 0 ]]; then
    echo "shard $i failed (exit $rc), see $out/logs/shard_$i.log:" >&2
    tail -n 5 "$out/logs/shard_$i.log" >&2
    [[ $status -eq 0 ]] && status=$rc
  fi
done
[[ $status -ne 0 ]] && exit "$status"
exec "$py" experiments/sweep.py --out "$out" --merge-only "$@"
