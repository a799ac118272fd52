#!/usr/bin/env bash
# N seeds of one method at once on the visible GPU, as stablebptt's seeds share theirs in one program:
# every '{seed}' in the command line becomes 0..N-1, each process gets 1/N of the GPU's memory, its
# output goes to LOGS/seed<i>.log; waits for all and exits non-zero if any failed.
#
#   benchmarks/envs_vs_apg/seeds_together.sh 5 LOGS 'python3 benchmarks/envs_vs_apg/ppo_baseline.py --seed0 {seed} ...'
set -u
n=$1; logs=$2; command=$3
mkdir -p "$logs"
fraction=$(python3 -c "print(round(0.9 / $n, 3))")
pids=()
for ((seed = 0; seed < n; seed++)); do
  XLA_PYTHON_CLIENT_MEM_FRACTION=$fraction bash -c "${command//\{seed\}/$seed}" > "$logs/seed$seed.log" 2>&1 &
  pids+=($!)
done
status=0
for pid in "${pids[@]}"; do wait "$pid" || status=1; done
exit $status
