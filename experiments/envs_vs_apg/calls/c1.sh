# Call 1: stablebptt R and C (3 seeds in one program per flow) on CartpoleSwingup and AcrobotSwingup, 90 s each.
source experiments/envs_vs_apg/device_env.sh
D=experiments/envs_vs_apg; O=$OUT/c1; mkdir -p $O; sha1sum stablebptt/*.py | sha1sum
for E in CartpoleSwingup AcrobotSwingup; do
  timeout 270 python3 $D/stablebptt_half.py --envs $E --modes R,C --seeds 3 --budget 90 --eval-every 40 --horizon 100 --batch 64 --out $O
done
cd $OUT && tar czf c1.tgz c1 && rm -rf c1
