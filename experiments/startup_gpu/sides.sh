# Sourced by table.sh and grid_compile.sh after install_wheels.sh: enter_side WHICH enters the
# checkout of one side of a side-by-side measurement, "after" (this one) or "before" ($BASELINE,
# default .baseline),
# with its package laid out and first on the path.
ROOT=$PWD
enter_side() {
  local dir=$ROOT; [ "$1" = before ] && dir=$ROOT/${BASELINE:-.baseline}
  cd "$dir" && link_package . && compile_checkout . && export PYTHONPATH=/tmp/site:$dir
}
