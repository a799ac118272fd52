# Cold starts of one train.py command at two checkouts in turn, ROUNDS times, each with an empty
# compile cache: on a machine that drifts from minute to minute, sides that alternate compare like
# with like. BEFORE and AFTER are checkouts laid out for import (stablebptt/tasks, commands and
# models linked to tasks/, scripts/ and models/, as experiments/install_wheels.sh lays them out).
#   BEFORE=/tmp/head AFTER=/tmp/after ROUNDS=3 bash experiments/cold_pairs_cpu.sh --model hopper.xml --epochs 1
# One line per run: the side, the round, train.py's time to the first update and the process's seconds.
PYTHON=${PYTHON:-python3}
for round in $(seq ${ROUNDS:-3}); do
  for side in before after; do
    dir=$BEFORE; [ $side = after ] && dir=$AFTER
    cache=$(mktemp -d)
    started=$(date +%s.%N)
    line=$(cd $dir && STABLEBPTT_COMPILE_CACHE=$cache PYTHONPATH=$dir $PYTHON scripts/train.py "$@" --no-progress \
      --out $cache/run 2>&1 | grep -o "time to the first update: [0-9]* s")
    echo "$side $round: $line; $($PYTHON -c "print(round($(date +%s.%N) - $started, 1))") s in all"
    rm -rf $cache
  done
done
