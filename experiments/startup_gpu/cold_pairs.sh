# Cold starts of one Playground environment, this checkout ("after") and $BASELINE ("before", as in
# table.sh) in turn, ROUNDS times (default 2), each an env_phases.sh cold run: on a machine whose cold
# starts drift by 10-20 s from call to call, sides that alternate in one call compare like with like.
#   BASELINE=.baseline-5185a6e bash experiments/startup_gpu/cold_pairs.sh CartpoleSwingup 2
# Logs: $OUT/{after,before}-{round}/; one line per run with train.py's time to the first update.
source experiments/install_wheels.sh
source experiments/startup_gpu/sides.sh
for round in $(seq ${2:-2}); do
  for side in after before; do
    (enter_side $side && mkdir -p $OUT/$side-$round \
      && OUT=$OUT/$side-$round RUNS=cold bash $ROOT/experiments/startup_gpu/env_phases.sh "$1" > $OUT/$side-$round/summary.txt 2>&1
     echo "$side $round: $(grep -E 'first update|wall' $OUT/$side-$round/summary.txt | tr '\n' ' ')")
  done
done
