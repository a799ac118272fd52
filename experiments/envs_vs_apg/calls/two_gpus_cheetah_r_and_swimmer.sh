# Two GPUs at once:
#   GPU 0: stablebptt R on CheetahRun, seeds 0-2 in one program, 450 s (the budget of its C row);
#   GPU 1: SwimmerSwimmer6 through experiments/env_survey.py with 8 times the training states of the suite survey
#          (128, in batches of 32), to tell overfitting 16 random targets from a failure to train.
#   bash experiments/envs_vs_apg/calls/two_gpus_cheetah_r_and_swimmer.sh CALL
CALL=$1
source experiments/envs_vs_apg/device_env.sh
D=experiments/envs_vs_apg; O=$OUT/$CALL; mkdir -p $O/stablebptt $O/survey; sha1sum stablebptt/*.py | sha1sum
CUDA_VISIBLE_DEVICES=0 timeout 560 python3 $D/stablebptt_half.py --envs CheetahRun --modes R --seeds 3 --budget 450 \
  --eval-every 40 --horizon 100 --batch 64 --min-timing-updates 2 --out $O/stablebptt > $O/stablebptt/out.txt 2>&1 &
CUDA_VISIBLE_DEVICES=1 python3 experiments/env_survey.py --envs SwimmerSwimmer6 --steps 50 --episode-length 200 \
  --epochs 40 --train-size 128 --test-size 64 --batch 32 --timeout 540 --out $O/survey/swimmer > $O/survey/out.txt 2>&1 &
wait
tail -3 $O/stablebptt/out.txt $O/survey/out.txt | cut -c1-300
(cd $OUT && tar czf $CALL.tgz $CALL && rm -rf $CALL)
