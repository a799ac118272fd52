# Call 3: Brax APG on AcrobotSwingup seed 2 and CheetahRun seeds 0-2, 90 s each, one after another.
source experiments/envs_vs_apg/device_env.sh
D=experiments/envs_vs_apg; O=$OUT/c3; mkdir -p $O; sha1sum stablebptt/*.py | sha1sum
timeout 120 python3 $D/apg_baseline.py --envs AcrobotSwingup --seed0 2 --seeds 1 --budget 90 --eval-every 30 --variants shipped,iter1,iter1+saferew --brax-eval none --out $O
timeout 440 python3 $D/apg_baseline.py --envs CheetahRun --seeds 3 --budget 90 --eval-every 30 --variants shipped,iter1,iter1+saferew --sticky-variant --brax-eval none --out $O
cd $OUT && tar czf c3.tgz c3 && rm -rf c3
