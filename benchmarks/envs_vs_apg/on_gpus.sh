#!/usr/bin/env bash
# One method per GPU, all at once: each command line given runs alone on its own GPU
# (CUDA_VISIBLE_DEVICES=i, in the order given), its output in LOGS/gpu<i>.log; waits for all and
# exits non-zero if any failed. Timings of methods so run never share a GPU.
#
#   benchmarks/envs_vs_apg/on_gpus.sh LOGS 'stablebptt train --env CheetahRun --seeds 5 --budget 300 --out RUNS/CheetahRun' \
#       'python3 benchmarks/envs_vs_apg/ppo_baseline.py --envs CheetahRun ...'
set -u
logs=$1; shift
mkdir -p "$logs"
pids=()
gpu=0
for command in "$@"; do
  CUDA_VISIBLE_DEVICES=$gpu bash -c "$command" > "$logs/gpu$gpu.log" 2>&1 &
  pids+=($!)
  gpu=$((gpu + 1))
done
status=0
for pid in "${pids[@]}"; do wait "$pid" || status=1; done
exit $status
