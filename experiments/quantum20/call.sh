# The quantum grid at 20 seeds (720 cells, 1000 epochs) on one host with two GPUs, in calls of under
# 10 minutes: seeds 0-9 train on GPU 0 and seeds 10-19 on GPU 1, as two pieces of one grid
# (scripts/sweep.py --seed-range). Each call resumes both pieces from their checkpoints and stops them
# after LIMIT seconds; the call that finds both pieces done merges them and writes the grid's report
# (--merge), which comes back as $OUT/quantum20_report.tgz.
#   bash experiments/quantum20/call.sh LIMIT
LIMIT=${1:-500}
source experiments/install_wheels.sh
export STABLEBPTT_COMPILE_CACHE=/tmp/q20_cache
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
SWEEP="python3 scripts/sweep.py --preset quantum --seeds 20 --out /tmp/q20"
for GPU in 0 1; do
  CUDA_VISIBLE_DEVICES=$GPU $SWEEP --seed-range $((GPU * 10)):$((GPU * 10 + 10)) --time-limit $LIMIT \
    >> /tmp/q20_piece$GPU.log 2>&1 &
done
wait
for GPU in 0 1; do echo "== piece $GPU"; tr '\r' '\n' < /tmp/q20_piece$GPU.log | grep -v '^\s*$' | tail -n 6 | cut -c1-250; done
cp /tmp/q20_piece0.log /tmp/q20_piece1.log $OUT/
if grep -q "^done: piece" /tmp/q20_piece0.log && grep -q "^done: piece" /tmp/q20_piece1.log; then
  $SWEEP --merge > $OUT/merge.log 2>&1; tail -n 30 $OUT/merge.log
  # the report's files and every call's record; the cells' folders stay behind (about 80 MB)
  (cd /tmp/q20 && { find quantum -maxdepth 1 -type f; find quantum -path '*/sweeps/*.json'; find quantum -name piece.json; } \
     | tar czf $OUT/quantum20_report.tgz -T -)
  ls -la $OUT
fi
