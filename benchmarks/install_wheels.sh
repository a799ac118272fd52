# Sourced on a machine without the dependencies on its package index (a GPU machine that cannot reach
# one): installs the cp312 wheels in .whl/ once per machine into /tmp/site and puts it and the
# checkout on the path (stablebptt is imported from the checkout). The wheels: mujoco, mujoco-core,
# mujoco-mjx and their dependencies, and for the environments playground and brax (warp-lang is not
# needed: MJX runs with impl="jax"); on a machine whose Python already holds JAX, optax, flax,
# orbax-checkpoint, matplotlib, scipy, etils, lxml and absl, these, at constraints.txt's versions:
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
#     --platform any -d .whl mujoco==4.0.0 mujoco-core==4.0.0 mujoco-mjx==3.17.0 \
#     playground==0.2.0 brax==0.14.2 trimesh==5.2.0 ml_collections==1.1.0 mediapy==1.2.7 jaxopt==0.8.5
# Training and the benchmarks import neither glfw nor PyOpenGL (MUJOCO_GL=disable below: mujoco lists
# them, for its windows and renderers) nor mujoco-studio (12.8 MB: MuJoCo Studio's application and its
# renderer, mujoco.studio and mujoco._render_filament; mujoco lists it too), and nothing imports
# mujoco-mjx's test_data/ (6.5 MB of the wheel's 7.3 MB, meshes; `zip -q -d .whl/mujoco_mjx-*.whl
# 'mujoco/mjx/test_data/*'` drops them) or reads playground's images (7.5 MB: the terrains and pictures
# of its locomotion and manipulation robots, no dm_control suite env's; `zip -q -d .whl/playground-*.whl
# '*.png'`): without them the wheels take 12 MB, where a machine that copies the checkout with them at
# most 64 MiB has room for run folders to resume (a HopperStand run of 5 seeds: 9 MB) and the compile
# cache of their first start.
# The packages are byte-compiled as pip installs them for a user: the machine's Python writes no
# bytecode of its own (PYTHONDONTWRITEBYTECODE), and compiling every module's source at each start
# cost about 1.8 s of a warm start there. So is the checkout, at every call (only what changed).
# Commands started at once (one per GPU) install one after another: two pip installs into one target
# fail each other.
mkdir -p /tmp/site
exec {install_lock}> /tmp/site.lock
flock "$install_lock"
if [ ! -f /tmp/site/.installed ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && python3 -m compileall -q -j 0 /tmp/site > /dev/null \
    && touch /tmp/site/.installed || { echo "wheel install failed"; exit 1; }
fi
flock -u "$install_lock"
exec {install_lock}>&-
compile_checkout() { python3 -m compileall -q -j 0 ${1:-.}/stablebptt > /dev/null; }
compile_checkout
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 MUJOCO_GL=disable

