# Brax APG alone on the GPU (one process, seed 0), 240 s budget, on CartpoleSwingup then AcrobotSwingup: what
# APG reaches when its seed does not share the GPU with the other two.
#   bash experiments/envs_vs_apg/calls/apg_alone.sh CALL
CALL=$1
source experiments/envs_vs_apg/device_env.sh
D=experiments/envs_vs_apg; O=$OUT/$CALL; mkdir -p $O; sha1sum stablebptt/*.py | sha1sum
for E in CartpoleSwingup AcrobotSwingup; do
  timeout 272 python3 $D/apg_baseline.py --envs $E --seed0 0 --seeds 1 --budget 240 --eval-every 30 \
    --variants shipped --brax-eval none --out $O/apg_alone > $O/out_$E.txt 2>&1
  grep -h -e "->" -e Error $O/out_$E.txt | cut -c1-400
  (cd $OUT && tar czf $CALL.tgz $CALL)
done
(cd $OUT && rm -rf $CALL)
