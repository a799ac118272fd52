# CheetahRun (contacts, 4 solver iterations): stablebptt C, seeds 0-2 in one program, 450 s of training wall time,
# set-up and compile included (at 240 s its set-up and compile had not ended). Brax APG as shipped stops at its
# first update there: reverse mode cannot pass MJX's solver loop.
#   bash experiments/envs_vs_apg/calls/cheetah_long.sh CALL
CALL=$1
source experiments/envs_vs_apg/device_env.sh
D=experiments/envs_vs_apg; O=$OUT/$CALL; mkdir -p $O; sha1sum stablebptt/*.py | sha1sum
timeout 575 python3 $D/stablebptt_half.py --envs CheetahRun --modes C --seeds 3 --budget 450 --eval-every 40 \
  --horizon 100 --batch 64 --min-timing-updates 2 --out $O/stablebptt
(cd $OUT && tar czf $CALL.tgz $CALL && rm -rf $CALL)
