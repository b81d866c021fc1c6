#!/bin/bash
# One shard of a sweep per SLURM array task; submit with scripts/slurm_submit.sh (which also
# queues the merge), or by hand from the repository root:
#
#   SWEEP_DIR=/shared/runs/sweep1e6 sbatch --array=0-15 scripts/slurm_sweep.sh --seeds 10 ...
#
# Task i of an array of N computes every N-th chunk (--shard-index i --num-shards N) into
# $SWEEP_DIR/chunks; SWEEP_DIR must be on a filesystem shared by every node (NFS, Lustre, GPFS):
# the shards and the merge all read and write that one folder. Every task must get the same sweep
# arguments ("$@"): the first shard records them in $SWEEP_DIR/chunks/sweep_settings.json and a
# shard or merge with other settings is refused (exit code 2). A failed or preempted task can be
# resubmitted alone (sbatch --array=<i> ...): finished chunks are skipped.
#
# The #SBATCH lines are defaults; options given to sbatch on the command line override them.
#SBATCH --job-name=hec-sweep
#SBATCH --array=0-7                # N shards: 0-(N-1); override with sbatch --array=0-<N-1>
#SBATCH --nodes=1
#SBATCH --ntasks=1
#SBATCH --cpus-per-task=8
#SBATCH --gres=gpu:1               # one or more GPUs per shard (the shard splits each chunk)
#SBATCH --time=02:00:00
#SBATCH --output=slurm-%A_%a.out   # %A: array job id, %a: task id
set -euo pipefail

: "${SWEEP_DIR:?set SWEEP_DIR to the sweep folder on a shared filesystem}"
: "${SLURM_ARRAY_TASK_ID:?submit as a job array (sbatch --array=0-<N-1>)}"
# sbatch runs a copy of this script: work from the folder it was submitted from (the repository)
cd "${HEC_JAX_ROOT:-${SLURM_SUBMIT_DIR:-.}}"
# a compilation cache on the shared filesystem: compiled once, reused by the later tasks
export HEC_JAX_CACHE="${HEC_JAX_CACHE:-$SWEEP_DIR/.jax_cache}"

exec "${PYTHON:-python}" experiments/sweep.py --out "$SWEEP_DIR" \
  --shard-index "$SLURM_ARRAY_TASK_ID" --num-shards "$SLURM_ARRAY_TASK_COUNT" "$@"
