# Where a Playground environment's start goes on a GPU: `train.py --env` run cold (an empty compile
# cache) and then warm (the same command again), each line of JAX's compile log (every trace,
# lowering and compile over a tenth of a second) stamped with the milliseconds since logging began
# (at the process's first import of JAX, about a second in), and JAX's own timings of its stages
# (its compile cache's key, its reads) where they took over a tenth of a second.
#   bash experiments/startup_gpu/env_phases.sh CartpoleSwingup
source experiments/install_wheels.sh
export STABLEBPTT_COMPILE_CACHE=${PHASES_CACHE:-$(mktemp -d /tmp/phases_cache_XXXX)}  # PHASES_CACHE=DIR RUNS=warm: again, warm
for run in ${RUNS:-cold warm}; do
  started=$(date +%s.%N)
  python3 -c "
import logging, runpy, sys
logging.basicConfig(format='%(relativeCreated)7.0f ms  %(message)s')
import jax
jax.config.update('jax_log_compiles', True)
log = logging.getLogger('phases')
jax.monitoring.register_event_duration_secs_listener(
    lambda event, seconds, **kwargs: seconds > 0.1 and log.warning(f'{event} {seconds:.3f} sec'))
sys.argv = ['scripts/train.py', '--env', '$1', '--epochs', '1', '--no-progress', '--out', '$(mktemp -d -u /tmp/phases_XXXX)']
runpy.run_path('scripts/train.py', run_name='__main__')" > $OUT/phases_$1_$run.log 2>&1
  echo "$(python3 -c "print(round($(date +%s.%N) - $started, 1))") s wall" >> $OUT/phases_$1_$run.log
  echo "== $run"
  grep -E "Finished (tracing|jaxpr|XLA)|/jax/" $OUT/phases_$1_$run.log | awk '{ if ($(NF-1) + 0 > 0.1) print }' | cut -c1-140
  grep -E "time to the first update|s wall" $OUT/phases_$1_$run.log
done
