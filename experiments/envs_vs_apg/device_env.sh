# Sourced at the start of a device call: the carried wheels installed and on the path, then what the
# machine and its packages are.
source experiments/install_wheels.sh
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
python3 -c "import jax, mujoco, brax, mujoco_playground; from mujoco import mjx; print('jax', jax.__version__, jax.devices(), 'mujoco', mujoco.__version__, 'brax', brax.__version__)" 2>&1 | grep -v -i "warp"
