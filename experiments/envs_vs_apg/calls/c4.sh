# Call 4: stablebptt C (3 seeds in one program) on CartpoleSwingup and AcrobotSwingup, 90 s each.
source experiments/envs_vs_apg/device_env.sh
D=experiments/envs_vs_apg; O=$OUT/c4; mkdir -p $O; sha1sum stablebptt/*.py | sha1sum
for E in CartpoleSwingup AcrobotSwingup; do
  timeout 283 python3 $D/stablebptt_half.py --envs $E --modes C --seeds 3 --budget 90 --eval-every 40 --horizon 100 --batch 64 --out $O/$E
done
cd $OUT && tar czf c4.tgz c4 && rm -rf c4
