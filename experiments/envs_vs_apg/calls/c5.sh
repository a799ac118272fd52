# Call 5: APG update throughput at stablebptt's program size (horizon 100, 192 envs = 3 seeds x 64) on CartpoleSwingup,
# then Brax APG on CheetahRun seeds 1-2 (variant iter1, as seed 0 needed), 90 s each.
source experiments/envs_vs_apg/device_env.sh
D=experiments/envs_vs_apg; O=$OUT/c5; mkdir -p $O; sha1sum stablebptt/*.py | sha1sum
timeout 130 python3 $D/apg_baseline.py --envs CartpoleSwingup --seeds 1 --budget 75 --eval-every 1000 --variants shipped --set horizon_length=100 --set num_envs=192 --throughput --brax-eval none --out $O
timeout 330 python3 $D/apg_baseline.py --envs CheetahRun --seed0 1 --seeds 2 --budget 90 --eval-every 30 --variants iter1,iter1+saferew --brax-eval none --out $O
cd $OUT && tar czf c5.tgz c5 && rm -rf c5
