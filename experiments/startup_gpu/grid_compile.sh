# The cart-pole grid's own programs (1-4 poles, 20 seeds: 240 cells each), compiled cold and run for one
# epoch (EPOCHS to run more and see the epochs' price), at this checkout and at d49bb4f (.baseline, as in table.sh); each program's compile time is in
# the sweep's record, which comes back as $OUT/grid-{after,before}.json.
#   [EPOCHS=200] bash experiments/startup_gpu/grid_compile.sh after before
source experiments/install_wheels.sh
source experiments/startup_gpu/sides.sh
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
for which in "$@"; do
  (
    enter_side "$which"
    python3 scripts/sweep.py --preset cartpole --seeds 20 --epochs ${EPOCHS:-1} --no-compile-cache --out /tmp/grid_$which-${EPOCHS:-1}-$$
  ) > $OUT/grid-$which.log 2>&1
  cp /tmp/grid_$which-${EPOCHS:-1}-$$/cartpole/sweeps/*.json $OUT/grid-$which.json
  python3 -c "import json; d = json.load(open('$OUT/grid-$which.json')); print('$which', d['device_kind'], [(p['complexity'], round(p['compile_seconds'], 1), round(p['train_seconds'], 1)) for p in d['programs']], round(d['wall_seconds_this_call'], 1))"
done
