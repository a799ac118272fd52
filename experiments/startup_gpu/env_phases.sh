# Where a Playground environment's cold start goes on a GPU: one cold `train.py --env` run with
# JAX_LOG_COMPILES, listing every trace, lowering and compile over half a second, in order.
#   bash experiments/startup_gpu/env_phases.sh CartpoleSwingup
source experiments/install_wheels.sh
JAX_LOG_COMPILES=1 python3 -X importtime scripts/train.py --env "$1" --epochs 1 --no-compile-cache --no-progress \
  --out $(mktemp -d -u /tmp/phases_XXXX) > $OUT/phases_$1.log 2>&1
grep -E "Finished (tracing|jaxpr|XLA)" $OUT/phases_$1.log | sed 's/.*Finished/Finished/' | awk '{ if ($(NF-1) + 0 > 0.5) print }'
grep -E "time to the first update" $OUT/phases_$1.log
