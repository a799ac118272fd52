# One env side by side, 240 s of training wall time each, set-up and compile included:
#   bash experiments/envs_vs_apg/calls/pair.sh CALL ENV
# Brax APG (apg.train's defaults, as shipped) with seeds 0-2 at the same time, one process each on the one GPU
# (no memory preallocation), as stablebptt's three seeds share the GPU in one program; then stablebptt C,
# seeds 0-2 in one compiled program. The records are packed into $OUT/CALL.tgz after each half.
CALL=$1; E=$2
source experiments/envs_vs_apg/device_env.sh
D=experiments/envs_vs_apg; O=$OUT/$CALL; mkdir -p $O/apg; sha1sum stablebptt/*.py | sha1sum
for S in 0 1 2; do
  XLA_PYTHON_CLIENT_PREALLOCATE=false timeout 280 python3 $D/apg_baseline.py --envs $E --seed0 $S --seeds 1 \
    --budget 240 --eval-every 30 --variants shipped --brax-eval none --out $O/apg > $O/apg/out_s$S.txt 2>&1 &
done
wait
grep -h -e "->" -e Error $O/apg/out_s*.txt | cut -c1-400
(cd $OUT && tar czf $CALL.tgz $CALL)
timeout 292 python3 $D/stablebptt_half.py --envs $E --modes C --seeds 3 --budget 240 --eval-every 30 \
  --horizon 100 --batch 64 --out $O/stablebptt
(cd $OUT && tar czf $CALL.tgz $CALL && rm -rf $CALL)
