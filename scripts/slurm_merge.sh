#!/bin/bash
# The merge of a sharded sweep: reads every chunk under $SWEEP_DIR/chunks, writes
# $SWEEP_DIR/metrics.json and peak_ratio_map.png. Queued by scripts/slurm_submit.sh after the
# array (--dependency=afterok:<array job id>); by hand:
#
#   SWEEP_DIR=/shared/runs/sweep1e6 sbatch --dependency=afterok:<jobid> scripts/slurm_merge.sh <same args>
#
# Give it the sweep arguments of the shards: a merge with other settings is refused (exit code 2).
#SBATCH --job-name=hec-sweep-merge
#SBATCH --nodes=1
#SBATCH --ntasks=1
#SBATCH --cpus-per-task=2
#SBATCH --time=00:30:00
#SBATCH --output=slurm-%j-merge.out
set -euo pipefail

: "${SWEEP_DIR:?set SWEEP_DIR to the sweep folder on a shared filesystem}"
cd "${HEC_JAX_ROOT:-${SLURM_SUBMIT_DIR:-.}}"
exec "${PYTHON:-python}" experiments/sweep.py --out "$SWEEP_DIR" --merge-only "$@"
