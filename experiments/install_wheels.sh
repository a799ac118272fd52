# Sourced at the start of a device call: installs the carried wheels (.whl) once per machine into
# /tmp/site, lays the package out as an install would, and puts both on the path (stablebptt is
# imported from the repo root).
# The packages are byte-compiled as pip installs them for a user: the machine's Python writes no
# bytecode of its own (PYTHONDONTWRITEBYTECODE), and compiling every module's source at each start
# cost about 1.8 s of a warm start there. So is the checkout, at every call (only what changed).
if [ ! -f /tmp/site/.installed ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && python3 -m compileall -q -j 0 /tmp/site > /dev/null \
    && touch /tmp/site/.installed || { echo "wheel install failed"; exit 1; }
fi
compile_checkout() { python3 -m compileall -q -j 0 ${1:-.}/stablebptt ${1:-.}/tasks ${1:-.}/scripts > /dev/null; }
compile_checkout
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 MUJOCO_GL=disable
# The repository's tasks/, scripts/ and models/ as stablebptt.tasks, .commands and .models, in the
# checkout at DIR (default: this one).
link_package() { for link in tasks:tasks commands:scripts models:models; do ln -sfn ../${link#*:} ${1:-.}/stablebptt/${link%%:*}; done; }
link_package
