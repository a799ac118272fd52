# Sourced at the start of a device call: installs the carried wheels (.whl) once per machine and sets the paths.
# stablebptt itself is imported from the repo root (only the package stablebptt/ is needed here).
if [ ! -f /tmp/site/.installed ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && touch /tmp/site/.installed || { echo "wheel install failed"; exit 1; }
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 MUJOCO_GL=disable
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
python3 -c "import jax, mujoco, brax, mujoco_playground; from mujoco import mjx; print('jax', jax.__version__, jax.devices(), 'mujoco', mujoco.__version__, 'brax', brax.__version__)" 2>&1 | grep -v -i "warp"
