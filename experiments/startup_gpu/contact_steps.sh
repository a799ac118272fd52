# A contact scene's training on one GPU through the generated rigid-body terms (the default) and through
# MJX's stages: time to the first update and each epoch's seconds, per model and pipeline, cold.
#   bash experiments/startup_gpu/contact_steps.sh hopper cheetah   (carry dm_control's suite folder)
#   [PIPELINES=lean] [EPOCHS=2] [BASELINE=dir] bash ... --before hopper   (the lean pipeline at $BASELINE's checkout)
source experiments/install_wheels.sh
if [ "$1" = --before ]; then
  shift; source experiments/startup_gpu/sides.sh; ln -sfn $ROOT/.cache $ROOT/${BASELINE:-.baseline}/.cache
  enter_side before; side=before-
fi
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
S=.cache/dm_control-1.0.50/dm_control/suite
for model in "$@"; do
  for pipeline in ${PIPELINES:-lean stages}; do
    out=/tmp/contact_$side$model-$pipeline-$$
    python3 scripts/train.py --model $S/$model.xml --pipeline $pipeline --epochs ${EPOCHS:-4} --no-compile-cache --no-progress \
      --out $out 2>&1 | grep "time to the first update" | sed "s/^/$side$model $pipeline: /"
    cp $out/metrics.csv $OUT/$side$model-$pipeline.csv
    echo "  epochs (s): $(tail -n +2 $out/metrics.csv | cut -d, -f8 | tr '\n' ' ')"
  done
done
