#!/bin/bash
# Submits a sweep as a SLURM job array of N shards plus a merge job that starts once every
# shard succeeded. Run it from the repository root on a login node:
#
#   SWEEP_DIR=/shared/runs/sweep1e6 scripts/slurm_submit.sh 16 --seeds 10 --rod-lengths ...
#
# SWEEP_DIR must be on a filesystem that every compute node mounts (the shards write their chunks
# there, the merge reads them). Extra sbatch options (partition, account, ...) go in
# SBATCH_EXTRA, e.g. SBATCH_EXTRA="--partition=gpu --account=myproj". If a shard fails, the merge
# is not run (afterok): resubmit that task (sbatch --array=<i> scripts/slurm_sweep.sh <args>),
# then the merge (scripts/slurm_merge.sh <args>); finished chunks are skipped.
set -euo pipefail

if [[ $# -lt 1 || ! $1 =~ ^[1-9][0-9]*$ ]]; then
  echo "usage: SWEEP_DIR=<shared folder> $0 N_SHARDS [sweep arguments ...]" >&2
  exit 2
fi
: "${SWEEP_DIR:?set SWEEP_DIR to the sweep folder on a shared filesystem}"
n=$1
shift
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
export SWEEP_DIR
# shellcheck disable=SC2086  # SBATCH_EXTRA: several options on purpose
array=$(sbatch --parsable ${SBATCH_EXTRA:-} --array="0-$((n - 1))" --export=ALL \
  "$here/slurm_sweep.sh" "$@")
array=${array%%;*}  # "jobid;cluster" on federated clusters
# shellcheck disable=SC2086
merge=$(sbatch --parsable ${SBATCH_EXTRA:-} --dependency="afterok:$array" --export=ALL \
  "$here/slurm_merge.sh" "$@")
echo "shards: job array $array (${n} tasks); merge: job ${merge%%;*} (after all succeed)"
echo "results: $SWEEP_DIR/metrics.json"
