# GPU compile time against XLA's GPU autotuning: the 4-pole program with the cart-pole grid's settings
# (train.py's defaults, --unroll 5), cold (an empty compile cache each run), three epochs, once with
# XLA's defaults and once per flag set below. JAX_LOG_COMPILES gives each program's compile time;
# the epochs give the price in run time.
#   bash experiments/startup_gpu/xla_gpu_flags.sh [LABEL ...]   (default: the first three below)
source experiments/install_wheels.sh
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
run() {  # label, XLA_FLAGS
  echo "== $1: XLA_FLAGS='$2'"
  XLA_FLAGS="$2" JAX_LOG_COMPILES=1 python3 scripts/train.py --model stablebptt/models/cartpole_4.xml --epochs 3 --unroll 5 \
    --no-compile-cache --no-progress --out /tmp/xf_$1 > $OUT/$1.log 2>&1
  grep -E "XLA compilation of|Finished tracing" $OUT/$1.log | sed 's/.*Finished/Finished/' \
    | awk '{ if ($(NF-1) + 0 > 1.0) print }'
  grep -E "time to the first update|^done" $OUT/$1.log
  echo "epoch seconds: $(cut -d, -f8 /tmp/xf_$1/metrics.csv | tail -n +2 | tr '\n' ' ')"
  cp /tmp/xf_$1/metrics.csv $OUT/$1.csv
}
declare -A FLAGS=(
  [default]=""
  [autotune0]="--xla_gpu_autotune_level=0"
  [autotune0_notriton]="--xla_gpu_autotune_level=0 --xla_gpu_enable_triton_gemm=false"
  [autotune0_parallel16]="--xla_gpu_autotune_level=0 --xla_gpu_force_compilation_parallelism=16"
)
for label in "${@:-default autotune0 autotune0_notriton}"; do
  for one in $label; do run "$one" "${FLAGS[$one]}"; done
done
