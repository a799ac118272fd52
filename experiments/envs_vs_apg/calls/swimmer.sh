# SwimmerSwimmer6 through experiments/env_survey.py with 4 times the training states of the suite survey (64, in
# batches of 16, 16 epochs), to tell overfitting 16 random targets from a failure to train.
#   bash experiments/envs_vs_apg/calls/swimmer.sh CALL
CALL=$1
source experiments/envs_vs_apg/device_env.sh
O=$OUT/$CALL; mkdir -p $O; sha1sum stablebptt/*.py | sha1sum
python3 experiments/env_survey.py --envs SwimmerSwimmer6 --steps 50 --episode-length 200 --epochs 16 --train-size 64 \
  --test-size 16 --batch 16 --timeout 500 --out $O/swimmer > $O/out.txt 2>&1
tail -n 4 $O/out.txt | cut -c1-300
(cd $OUT && tar czf $CALL.tgz $CALL && rm -rf $CALL)
