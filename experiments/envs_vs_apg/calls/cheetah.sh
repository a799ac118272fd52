# CheetahRun (contacts, 4 solver iterations): stablebptt C, seeds 0-2 in one program, 240 s of training wall time
# (Brax APG as shipped stops at its first update there: reverse mode cannot pass MJX's solver loop); then the
# update's throughput at Brax APG's own size (horizon 32 x 1 env, one seed) on CartpoleSwingup and AcrobotSwingup.
#   bash experiments/envs_vs_apg/calls/cheetah.sh CALL
CALL=$1
source experiments/envs_vs_apg/device_env.sh
D=experiments/envs_vs_apg; O=$OUT/$CALL; mkdir -p $O; sha1sum stablebptt/*.py | sha1sum
timeout 345 python3 $D/stablebptt_half.py --envs CheetahRun --modes C --seeds 3 --budget 240 --eval-every 30 \
  --horizon 100 --batch 64 --out $O/stablebptt
(cd $OUT && tar czf $CALL.tgz $CALL)
timeout 200 python3 $D/stablebptt_half.py --throughput --envs CartpoleSwingup,AcrobotSwingup --modes C --seeds 1 \
  --horizon 32 --batch 1 --train-batches 1 --out $O/throughput
(cd $OUT && tar czf $CALL.tgz $CALL && rm -rf $CALL)
