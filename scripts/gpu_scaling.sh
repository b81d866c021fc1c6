#!/usr/bin/env bash
# Multi-GPU scaling of one host (issue 25; docs/benchmarks_gpu.md, "Four GPUs"):
#   1. benchmarks/sweep.py --per-device: the learning loop on 1, 2, 4, ... GPUs (weak scaling,
#      65536 runs per GPU) against MuJoCo C on all host cores, in one run;
#   2. experiments/sweep.py: the 10^5- and 10^6-condition sweeps on all GPUs and on one
#      (CUDA_VISIBLE_DEVICES=0), compile and running time apart.
# Usage, from the repository root of an installed checkout (pip install -e ".[cuda12]"):
#   scripts/gpu_scaling.sh OUT_DIR
# Writes OUT_DIR/bench_scaling.txt and OUT_DIR/sweep_<size>_<gpus>.txt; the sweeps' folders go
# under OUT_DIR/sweeps/ (each a complete run folder).
set -euo pipefail
out=${1:?usage: scripts/gpu_scaling.sh OUT_DIR}
mkdir -p "$out/sweeps"
py=${PYTHON:-python3}
CG8="--solver-iterations 8 --ls-iterations 8 --solver cg --jacobian sparse"
$py benchmarks/sweep.py --float32 --batch 65536 --per-device --steps 1000 --c-repeats 1 \
  --grad-batch 0 $CG8 --kernels triton-inside | tee "$out/bench_scaling.txt"
grid="--rod-lengths $(seq -s ' ' 0.50 0.02 0.68) --cube-masses $(seq -s ' ' 0.50 0.05 0.95)
  --release-angles $(seq -s ' ' -0.40 -0.02 -0.58) --hinge-dampings $(seq -s ' ' 0 0.001 0.009)
  --swings 1 --swing-s 3 --float32 --chunk 100000 $CG8 --kernel triton --no-nets-outside"
for size in 1e5 1e6; do
  seeds=10; [ "$size" = 1e6 ] && seeds=100
  for gpus in all 1; do
    name="${size}_${gpus}"
    start=$(date +%s)
    if [ "$gpus" = 1 ]; then
      CUDA_VISIBLE_DEVICES=0 $py experiments/sweep.py --out "$out/sweeps/$name" --seeds $seeds $grid \
        >"$out/sweep_$name.txt" 2>&1
    else
      $py experiments/sweep.py --out "$out/sweeps/$name" --seeds $seeds $grid >"$out/sweep_$name.txt" 2>&1
    fi
    echo "process wall $(($(date +%s) - start)) s" >>"$out/sweep_$name.txt"
    echo "$name: $(grep -E 'chunks in' "$out/sweep_$name.txt" | tail -1); $(tail -1 "$out/sweep_$name.txt")"
  done
done
