#!/usr/bin/env bash
# One method per GPU, all at once: each command line given runs alone on its own GPU
# (CUDA_VISIBLE_DEVICES=i, in the order given), its output in LOGS/gpu<i>.log and its exit status in
# LOGS/gpu<i>.status once it ends; waits for all and exits non-zero if any failed. Timings of methods
# so run never share a GPU.
#
#   benchmarks/envs_vs_apg/on_gpus.sh LOGS 'stablebptt train --env CheetahRun --seeds 5 --budget 300 --out RUNS/CheetahRun' \
#       'python3 benchmarks/envs_vs_apg/ppo_baseline.py --envs CheetahRun ...'
#
# Runs that outlive the shell starting them (a budget of 900 s from a shell limited to 10 minutes): --detach
# starts each in a session of its own, which outlives the shell, and returns at once; --wait LOGS SECONDS
# then returns once all have ended (their status as above) or, after SECONDS, with status 3 and the
# commands still running. Write their run folders where the machine keeps them between shells.
#
#   benchmarks/envs_vs_apg/on_gpus.sh --detach LOGS 'COMMAND' 'COMMAND'
#   benchmarks/envs_vs_apg/on_gpus.sh --wait LOGS 560
set -u
ended() {  # every command started in LOGS has its status: 0 if all succeeded, 1 if any failed
  local status=0 started
  for started in "$1"/gpu*.log; do
    [ -f "${started%.log}.status" ] || return 2
    [ "$(cat "${started%.log}.status")" = 0 ] || status=1
  done
  return $status
}
if [ "${1:-}" = "--wait" ]; then
  logs=$2; until_seconds=$(( SECONDS + $3 ))
  while true; do
    ended "$logs"; status=$?
    [ $status -ne 2 ] && exit $status
    [ $SECONDS -ge $until_seconds ] && { echo "still running after $3 s: $logs"; exit 3; }
    sleep 5
  done
fi
detach=""
[ "${1:-}" = "--detach" ] && { detach=setsid; shift; }
logs=$1; shift
mkdir -p "$logs"
rm -f "$logs"/gpu*.status "$logs"/gpu*.log
gpu=0
for command in "$@"; do
  log="$logs/gpu$gpu.log"
  # the command in a shell of its own, so that its exit still writes the status
  CUDA_VISIBLE_DEVICES=$gpu $detach bash -c 'bash -c "$1"; echo $? > "$2"' run "$command" "${log%.log}.status" \
    > "$log" 2>&1 < /dev/null &
  gpu=$((gpu + 1))
done
[ -n "$detach" ] && exit 0
wait
ended "$logs"
