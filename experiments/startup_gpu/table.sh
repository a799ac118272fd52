# The GPU start-up table, side by side: the same bench command at this checkout ("after") and at
# d49bb4f ("before", the commit of the earlier GPU table), unpacked into .baseline by
#   git archive d49bb4f -- stablebptt tasks scripts models pyproject.toml | tar -x -C .baseline
# Each argument is WHICH:WHAT:NAMES, WHICH one of after/before, WHAT one of models/envs, e.g.
#   bash experiments/startup_gpu/table.sh after:models:1,2,3,4 before:models:1,2
# Models are the repository's cart-poles with the cart-pole grid's settings; envs take train.py's
# defaults for an environment. Tables and records come back as $OUT/gpu-{WHICH}-{WHAT}-{NAMES}.md/.json.
source experiments/install_wheels.sh
source experiments/startup_gpu/sides.sh
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
for part in "$@"; do
  IFS=: read -r which what names <<< "$part"
  name=gpu-$which-$what-${names//,/_}
  (
    enter_side "$which"
    if [ "$what" = models ]; then
      list=$(echo "$names" | sed 's/\([0-9]\)/models\/cartpole_\1.xml/g')
      python3 scripts/bench.py --startup --models "$list" --train-args '--epochs 1 --unroll 5' --timeout 150 --out $OUT/$name.md
    else
      python3 scripts/bench.py --startup --envs "$names" --env-args '--epochs 1' --timeout 270 --out $OUT/$name.md
    fi
  ) > $OUT/$name.log 2>&1
  echo "== $name"; grep '^|' $OUT/$name.md | tail -n +3 | cut -c1-200
done
