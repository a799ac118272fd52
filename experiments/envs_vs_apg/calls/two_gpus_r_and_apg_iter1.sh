# Two GPUs, two halves at once (each process sees one GPU, so neither slows the other):
#   GPU 0: stablebptt R, seeds 0-2 in one program, 240 s on CartpoleSwingup then on AcrobotSwingup (the budget of
#          the C rows and of Brax APG as shipped);
#   GPU 1: Brax APG's iter1 variant (one solver iteration: APG cannot pass the shipped model's solver loop) on
#          CheetahRun, seeds 0-2 at once, 450 s (the budget of stablebptt C's CheetahRun row).
#   bash experiments/envs_vs_apg/calls/two_gpus_r_and_apg_iter1.sh CALL
CALL=$1
source experiments/envs_vs_apg/device_env.sh
D=experiments/envs_vs_apg; O=$OUT/$CALL; mkdir -p $O/apg $O/stablebptt; sha1sum stablebptt/*.py | sha1sum
(for E in CartpoleSwingup AcrobotSwingup; do
   CUDA_VISIBLE_DEVICES=0 timeout 292 python3 $D/stablebptt_half.py --envs $E --modes R --seeds 3 --budget 240 \
     --eval-every 30 --horizon 100 --batch 64 --out $O/stablebptt > $O/stablebptt/out_$E.txt 2>&1
 done) &
for S in 0 1 2; do
  CUDA_VISIBLE_DEVICES=1 XLA_PYTHON_CLIENT_PREALLOCATE=false timeout 560 python3 $D/apg_baseline.py --envs CheetahRun \
    --seed0 $S --seeds 1 --budget 450 --eval-every 45 --variants iter1 --brax-eval none --out $O/apg \
    > $O/apg/out_s$S.txt 2>&1 &
done
wait
grep -h -e "->" -e Error $O/apg/out_s*.txt $O/stablebptt/out_*.txt | cut -c1-300
(cd $OUT && tar czf $CALL.tgz $CALL && rm -rf $CALL)
