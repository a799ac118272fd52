# Sourced at the start of a device call: installs the carried wheels (.whl) once per machine into
# /tmp/site, lays the package out as an install would, and puts both on the path (stablebptt is
# imported from the repo root).
if [ ! -f /tmp/site/.installed ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && touch /tmp/site/.installed || { echo "wheel install failed"; exit 1; }
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 MUJOCO_GL=disable
# The repository's tasks/, scripts/ and models/ as stablebptt.tasks, .commands and .models, in the
# checkout at DIR (default: this one).
link_package() { for link in tasks:tasks commands:scripts models:models; do ln -sfn ../${link#*:} ${1:-.}/stablebptt/${link%%:*}; done; }
link_package
