# Device smoke test: the heavy contact env for both halves, and APG's variant chain on the two kinds of failure.
source experiments/envs_vs_apg/device_env.sh
D=experiments/envs_vs_apg; O=$OUT/smoke; mkdir -p $O
sha1sum stablebptt/*.py | sha1sum
timeout 240 python3 $D/stablebptt_half.py --envs CheetahRun --modes C --seeds 3 --budget 60 --eval-every 20 --horizon 100 --batch 64 --out $O
timeout 200 python3 $D/apg_baseline.py --envs CheetahRun --seeds 1 --budget 30 --eval-every 10 --variants shipped,iter1,iter1+saferew,noconstraint+saferew --brax-eval none --out $O
timeout 120 python3 $D/apg_baseline.py --envs CartpoleSwingup --seeds 1 --budget 20 --eval-every 10 --variants shipped,noconstraint,saferew,noconstraint+saferew --brax-eval none --out $O
cd $OUT && tar czf smoke.tgz smoke && rm -rf smoke
