"""XLA:CPU runtime set-up: batched LAPACK calls running at once must not deadlock the intra-op pool.

jaxlib 0.10.2's LAPACK kernels (cholesky, triangular solve; MJX's Newton solver)
split a batch of at least ~200k flops into chunks queued on XLA's intra-op pool and
block the pool thread that runs them until the chunks are done. When as many such
calls run at once as the pool has threads, every thread waits and nobody runs the
chunks. ``stablebptt.one_cpu_thread()`` (every command calls it as it starts) gives the pool one thread
(PJRT_NPROC=1), with which the kernels run the whole batch in place; ``import stablebptt`` alone
changes nothing in the process.
"""
import importlib.util
import os
import subprocess
import sys
import textwrap

import pytest

from stablebptt.engine import compiling

from conftest import ROOT

# 16 independent triangular solves of 100 7x7 systems with 49 right-hand sides each
# (hopper's step-Jacobian solves, smaller batch): with a 2-thread pool this hangs
# within the first calls on a 2-core machine; fixed, 300 calls take about a second.
PROGRAM = textwrap.dedent("""
    import stablebptt
    stablebptt.one_cpu_thread()  # before JAX starts its CPU client
    import jax, jax.numpy as jnp
    key = jax.random.PRNGKey(0)
    chol = jnp.tril(jax.random.normal(key, (100, 7, 7))) + 21 * jnp.eye(7)
    rhs = [jax.random.normal(jax.random.fold_in(key, i), (100, 7, 49)) for i in range(16)]
    solve = jax.jit(lambda c, bs: [jax.lax.linalg.triangular_solve(c, b, left_side=True, lower=True) for b in bs])
    for _ in range(300):
        jax.block_until_ready(solve(chol, rhs))
    threads = [open(f"/proc/self/task/{t}/comm").read().strip() for t in os.listdir("/proc/self/task")]
    print("intra-op threads:", threads.count("tf_XLAEigen"))
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads thread names from /proc")
def test_concurrent_batched_lapack_calls_finish():
    env = {k: v for k, v in os.environ.items() if k not in ("PJRT_NPROC", "NPROC")}
    env["PYTHONPATH"] = str(ROOT)
    try:
        result = subprocess.run([sys.executable, "-c", "import os\n" + PROGRAM], env=env, capture_output=True,
                                text=True, timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail("concurrent batched LAPACK calls deadlocked XLA:CPU's intra-op pool")
    assert result.returncode == 0, result.stderr
    assert "intra-op threads: 1" in result.stdout, result.stdout


def test_one_cpu_thread_after_jaxs_first_computation_warns_and_before_it_is_silent():
    env = {**{k: v for k, v in os.environ.items() if k not in ("PJRT_NPROC", "NPROC")}, "PYTHONPATH": str(ROOT)}
    program = textwrap.dedent("""
        import warnings
        warnings.simplefilter("error")  # a warning fails the call that raises it
        import stablebptt, jax
        {before}
        try:
            stablebptt.one_cpu_thread()
            print("silent")
        except RuntimeWarning as warning:
            print(warning)
    """)
    said = [subprocess.run([sys.executable, "-c", program.format(before=before)], env=env, capture_output=True,
                           text=True, timeout=120) for before in ("", "jax.numpy.zeros(2).block_until_ready()")]
    assert [result.returncode for result in said] == [0, 0], [result.stderr for result in said]
    assert said[0].stdout == "silent\n"
    assert said[1].stdout.startswith("one_cpu_thread came after JAX's first computation"), said[1].stdout


def test_gpu_programs_compile_with_unchecked_autotuning_on_every_core_unless_xla_flags_say_otherwise(monkeypatch):
    """On a GPU every program compiles with XLA's autotuning unchecked (level 1), its kernels compiled
    on every usable core (``compiling.gpu_options``); an option the user put in XLA_FLAGS is left to
    XLA. A jaxlib that no longer knows an option's name fails the compile below, on any backend."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from stablebptt import timing

    x = jnp.arange(9.0).reshape(3, 3)
    np.testing.assert_array_equal(jax.jit(lambda a: a @ a, compiler_options=compiling.gpu_options())(x), x @ x)
    monkeypatch.setattr(compiling.jax, "default_backend", lambda: "gpu")
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=1")
    every_core = {"xla_gpu_autotune_level": 1, "xla_gpu_force_compilation_parallelism": timing.usable_cores()}
    assert compiling.compiler_options(False) == every_core
    assert compiling.compiler_options(True) == every_core  # the CPU's loop emitter stays the CPU's
    monkeypatch.setenv("XLA_FLAGS", "--xla_gpu_autotune_level=4")
    assert compiling.compiler_options(False) == {"xla_gpu_force_compilation_parallelism": timing.usable_cores()}


def test_large_scenes_compile_with_a_loop_emitter_this_xla_accepts_and_the_numbers_stay():
    """Programs holding a step of more than LARGE_STEP operations compile without XLA:CPU's fusion
    emitters (``training.LARGE_STEP_CPU_OPTIONS``; through them humanoid_CMU's kinematics ran for
    minutes per step). A jaxlib that no longer knows the option fails this compile; the option
    must change no result beyond rounding."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from stablebptt.engine.compiling import LARGE_STEP_CPU_OPTIONS, compiler_options

    if jax.default_backend() == "cpu":
        assert compiler_options(False) is None
        assert compiler_options(True) == LARGE_STEP_CPU_OPTIONS

    def chain(x):  # a deep elementwise chain whose operands many elements read, as a tree's kinematics fuse
        for _ in range(10):
            x = jnp.sin(jnp.concatenate([x[1:] - x[:-1], x[:1] * x[-1:]]) + jnp.cross(x[:3], x[-3:]).sum())
        return x

    x = jnp.linspace(0.1, 1.0, 8)
    with_loop_emitter = jax.jit(chain, compiler_options=LARGE_STEP_CPU_OPTIONS)(x)
    # The fusion emitters named: the tests' XLA_FLAGS turn them off (tests/conftest.py).
    with_fusion_emitters = jax.jit(chain, compiler_options={"xla_cpu_use_fusion_emitters": True})(x)
    np.testing.assert_allclose(with_loop_emitter, with_fusion_emitters, rtol=1e-5, atol=1e-6)
    assert np.all(np.isfinite(with_loop_emitter)) and np.ptp(with_loop_emitter) > 0


@pytest.mark.skipif(importlib.util.find_spec("warp") is None, reason="warp-lang is not installed: MJX has no Warp backend to leave out")
def test_train_and_sweep_load_mjx_without_its_warp_backend_and_warp_stays_importable():
    """train.py and sweep.py import MJX without its Warp backend (``cli.leave_out_unused_backends``) before
    parsing: MJX's JAX implementation still builds and steps a model, nothing is printed, and
    ``import warp`` works afterwards."""
    program = textwrap.dedent("""
        import sys
        from stablebptt.cli import leave_out_unused_backends
        leave_out_unused_backends()
        import mujoco
        from mujoco import mjx
        import mujoco.mjx.warp
        assert "mujoco.mjx.third_party.mujoco_warp" not in sys.modules and not mujoco.mjx.warp.WARP_INSTALLED
        assert sys.modules.get("warp", False) is not None  # the block is lifted
        model = mujoco.MjModel.from_xml_string('<mujoco><worldbody><body><joint type="slide"/><geom size=".1"/></body></worldbody></mujoco>')
        data = mjx.step(mjx.put_model(model), mjx.make_data(mjx.put_model(model)))
        assert float(data.qpos[0]) < 0  # it falls along the slide
        import warp  # noqa: F401
        print("ok")
    """)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    result = subprocess.run([sys.executable, "-c", program], env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout == "ok\n", result.stdout
    for script in ("train.py", "sweep.py"):  # first thing in main, before parsing imports the tasks
        main = (ROOT / "stablebptt" / "commands" / script).read_text().split("def main(", 1)[1]
        assert main.split("\n")[1].strip().startswith("leave_out_unused_backends()"), script


def test_the_commands_import_playground_without_pytorch_which_stays_importable(tmp_path):
    """Where PyTorch is installed, Playground's torch wrapper imports it; after ``cli.leave_out_unused_backends``
    (the commands' first call) Playground's registry loads without it, and ``import torch`` works afterwards.
    A stand-in ``torch`` module on the path plays the installed one."""
    pytest.importorskip("mujoco_playground")
    (tmp_path / "torch.py").write_text("STAND_IN = True\n")
    program = textwrap.dedent("""
        import sys
        from stablebptt.cli import leave_out_unused_backends
        if sys.argv[1] == "left out":
            leave_out_unused_backends()
        from stablebptt.envs import playground
        assert "CartpoleSwingup" in playground.names()
        from mujoco_playground._src import wrapper_torch
        print("torch" in sys.modules, wrapper_torch.torch is not None, end=" ")
        import torch
        print(torch.STAND_IN)
    """)
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{tmp_path}")
    for case, expected in (("left out", "False False True\n"), ("as installed", "True True True\n")):
        result = subprocess.run([sys.executable, "-c", program, case], env=env, capture_output=True, text=True, timeout=120)
        assert result.returncode == 0, result.stderr
        assert result.stdout == expected, (case, result.stdout)


def test_importing_the_package_leaves_the_process_environment_as_it_was():
    program = ("import os; before = dict(os.environ); import stablebptt, stablebptt.tasks, stablebptt.runs.run_folder; "
               "print(sorted(set(os.environ.items()) ^ set(before.items())))")
    env = {k: v for k, v in os.environ.items() if k not in ("PJRT_NPROC", "NPROC")}
    result = subprocess.run([sys.executable, "-c", program], env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]", result.stdout


def test_a_command_collects_garbage_less_often_and_leaves_a_threshold_chosen_otherwise():
    """The commands' process collects Python's garbage after 20,000 new objects (``rarer_garbage_collections``,
    called as ``stablebptt.commands`` is imported); ``import stablebptt`` alone leaves Python's threshold,
    and a threshold set higher, or 0 (collections off), stays as it was."""
    program = textwrap.dedent("""
        import gc
        import stablebptt
        alone = gc.get_threshold()[0]
        import stablebptt.commands
        command = gc.get_threshold()[0]
        kept = []
        for chosen in (0, 50_000):
            gc.set_threshold(chosen, 10, 10)
            stablebptt.rarer_garbage_collections()
            kept.append(gc.get_threshold()[0])
        print(alone, command, *kept)
    """)
    result = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert result.returncode == 0, result.stderr
    alone, command, off, higher = map(int, result.stdout.split()[-4:])
    from stablebptt.runtime import SPACED_COLLECTIONS
    assert alone < SPACED_COLLECTIONS == command == 20_000 and (off, higher) == (0, 50_000)
