"""Shared test set-up: the package imported first, and a float64 switch for single tests.

The tests import the installed package (``make`` installs it in editable mode), as users do.
"""
import os

# The tests are bound by XLA's compile time, not by their run time, and LLVM's optimisation passes are
# much of a CPU compile: the tests run without them, and so do the command lines they start, which
# inherit the variable. XLA's own graph passes still run; numbers differ from optimised code's in the
# last bits of float32 (instruction choice), which no test compares across the two.
# XLA:CPU's fusion emitters run an MLIR pipeline per fusion: the playground test's training epoch took
# 70 s of CPU to compile with them, 33 s with the loop emitter (what the product compiles large steps
# with, compiling.LARGE_STEP_CPU_OPTIONS). The tests use the loop emitter; the one test that compares
# the two emitters asks for the fusion emitters by name.
os.environ["XLA_FLAGS"] = (f"{os.environ.get('XLA_FLAGS', '')} --xla_backend_optimization_level=0"
                           " --xla_cpu_use_fusion_emitters=false").strip()

import atexit
import importlib.util
import contextlib
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import jax
import pytest

import stablebptt

stablebptt.one_cpu_thread()  # XLA:CPU's set-up, before JAX creates its CPU client
from stablebptt.runtime import COMPILE_CACHE_ENV, use_compile_cache

# One compilation cache for the session, its workers and the command lines the tests start included:
# a program compiled once (the same small run, resumed, killed, rendered, or built by tests on another
# worker) is loaded the next time. Never the user's own cache. The process that made it (pytest's
# own, which starts the workers) removes it at its exit; a worker finds it in its environment.
TESTS_CACHE_ENV = "STABLEBPTT_TESTS_COMPILE_CACHE"
if TESTS_CACHE_ENV not in os.environ:
    os.environ[TESTS_CACHE_ENV] = tempfile.mkdtemp(prefix="stablebptt-test-cache-")
    atexit.register(shutil.rmtree, os.environ[TESTS_CACHE_ENV], ignore_errors=True)
os.environ[COMPILE_CACHE_ENV] = os.environ[TESTS_CACHE_ENV]
use_compile_cache()

ROOT = Path(__file__).resolve().parent.parent  # the checkout: scripts are run from here

HAS_PLAYGROUND = importlib.util.find_spec("mujoco_playground") is not None
needs_playground = pytest.mark.skipif(not HAS_PLAYGROUND, reason="MuJoCo Playground is not installed "
                                                                  "(pip install 'stablebptt[playground]')")


def run_script(*args, env=None):
    return subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=900,
                          env={**os.environ, **(env or {})})


def train_in_process(capsys, *argv):
    """scripts/train.py's main in this process: (exit code, stderr lines)."""
    from stablebptt.commands import train as train_command
    try:
        code = train_command.main(list(argv))
    except SystemExit as exit_:
        code = exit_.code
    return code, [line for line in capsys.readouterr().err.splitlines() if line.strip()]


def refused_in_one_line(capsys, out, expected: str, *argv) -> str:
    """scripts/train.py's main given ``argv`` and ``--out out`` refuses it as bad input: exit code 2, one
    line on stderr naming ``expected``, and no run folder made. Returns the line."""
    code, err = train_in_process(capsys, *argv, "--out", str(out))
    assert code == 2 and len(err) == 1 and expected in err[0], err
    assert not os.path.exists(out), f"{out} was made by a refused command"
    return err[0]


@contextlib.contextmanager
def float64():
    """Run a block in float64 without flipping the whole session (other tests are float32)."""
    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", previous)


def jitted_anew(function):
    """``jax.jit`` of a new function object calling ``function``: jit reuses the trace of a function object
    it has traced before, so a function traced outside ``differentiable_mjx`` would keep MJX's own derivative
    and values inside it. The tests run MJX through it rather than eagerly, where it would compile each of its
    operations on its own."""
    return jax.jit(lambda *args: function(*args))


@pytest.fixture
def x64():
    with float64():
        yield


@pytest.fixture(params=["written out", "in arrays"])
def form(request, monkeypatch):
    """The generated step's terms of every size in one form, then the other (``rigid_body.make_scene``)."""
    from stablebptt.physics import rigid_body
    most = 1000 if request.param == "written out" else 0
    monkeypatch.setattr(rigid_body, "WRITTEN_OUT_DOFS", {"cpu": most, "gpu": most})
    return request.param


DM_CONTROL = "dm_control==1.0.50"  # the DeepMind Control Suite's MJCF files, as users find them


@pytest.fixture(scope="session")
def suite():
    """The folder of dm_control's suite/*.xml (with common/ and the dog's assets), fetched once from the
    package index into the checkout's .cache (dm_control itself is not installed)."""
    cache = ROOT / ".cache" / DM_CONTROL.replace("==", "-")
    folder = cache / "dm_control" / "suite"
    if not (folder / "walker.xml").is_file():
        cache.mkdir(parents=True, exist_ok=True)
        download = subprocess.run([sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--dest",
                                   str(cache), DM_CONTROL], capture_output=True, text=True)
        assert download.returncode == 0, f"cannot fetch {DM_CONTROL} from the package index: {download.stderr}"
        wheel = next(cache.glob("dm_control-*.whl"))
        with zipfile.ZipFile(wheel) as archive:
            archive.extractall(cache, [n for n in archive.namelist() if n.startswith("dm_control/suite/")])
        wheel.unlink()
    return folder
