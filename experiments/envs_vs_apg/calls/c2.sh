# Call 2: Brax APG (apg.train defaults) on CartpoleSwingup seeds 0-2 and AcrobotSwingup seeds 0-1, 90 s each, one after another.
source experiments/envs_vs_apg/device_env.sh
D=experiments/envs_vs_apg; O=$OUT/c2; mkdir -p $O; sha1sum stablebptt/*.py | sha1sum
timeout 340 python3 $D/apg_baseline.py --envs CartpoleSwingup --seeds 3 --budget 90 --eval-every 30 --variants shipped,noconstraint,saferew,noconstraint+saferew --sticky-variant --brax-eval none --out $O
timeout 225 python3 $D/apg_baseline.py --envs AcrobotSwingup --seeds 2 --budget 90 --eval-every 30 --variants shipped,iter1,iter1+saferew --sticky-variant --brax-eval none --out $O
cd $OUT && tar czf c2.tgz c2 && rm -rf c2
