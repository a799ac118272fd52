"""An environment's reward diagnosis (``adapter.diagnose_env``) traced and lowered once, then
compiled under each set of XLA options and run once: seconds to compile, and whether every set
classifies the reward the same. The compile cache is off.

    python benchmarks/diagnosis_compile.py CartpoleSwingup [AcrobotSwingup ...]
"""
import os
import sys
import time

os.environ.setdefault("JAX_ENABLE_COMPILATION_CACHE", "false")

import jax  # noqa: E402

from stablebptt.cli import leave_out_unused_backends  # noqa: E402
from stablebptt.engine.compiling import compiler_options  # noqa: E402
from stablebptt.envs import adapter, diagnosis, protocol  # noqa: E402
from stablebptt.timing import usable_cores

leave_out_unused_backends()
OPTION_SETS = {  # name -> the diagnosis's XLA options
    "training's": compiler_options() or {},
}
if jax.default_backend() == "gpu":
    OPTION_SETS.update({
        "autotune 0": {"xla_gpu_autotune_level": 0, "xla_gpu_force_compilation_parallelism": usable_cores()},
        "autotune 0, ptxas -O0": {"xla_gpu_autotune_level": 0, "xla_gpu_force_compilation_parallelism": usable_cores(),
                                  "xla_gpu_disable_gpuasm_optimizations": True},
        "autotune 0, LLVM -O0, ptxas -O0": {"xla_gpu_autotune_level": 0, "xla_gpu_force_compilation_parallelism": usable_cores(),
                                            "xla_gpu_disable_gpuasm_optimizations": True, "xla_backend_optimization_level": 0},
    })
else:
    OPTION_SETS.update({"LLVM -O0": {"xla_backend_optimization_level": 0},
                        "LLVM -O0, no expensive passes": {"xla_backend_optimization_level": 0,
                                                          "xla_llvm_disable_expensive_passes": True}})

OPTION_SETS["training's, again"] = OPTION_SETS["training's"]  # the first compile of a process warms XLA up

for name in sys.argv[1:]:
    env = protocol.load_env(name)
    task = adapter.env_task(env, horizon=1, diagnose=False)
    step, episode_length = task.dynamics.step, task.resolved["episode_length"]
    checks = diagnosis._gradient_checks(step)
    program = jax.jit(lambda key: checks(*diagnosis.sample_for_diagnosis(env, step, key, episode_length)))
    key = jax.random.PRNGKey(0)
    started = time.perf_counter()
    lowered = program.lower(key)
    print(f"{name}: trace and lower {time.perf_counter() - started:.1f} s", flush=True)
    for label, options in OPTION_SETS.items():
        started = time.perf_counter()
        compiled = lowered.compile(compiler_options=options)
        seconds = time.perf_counter() - started
        started = time.perf_counter()
        verdict = diagnosis._classify(*jax.device_get(compiled(key)))
        print(f"{name}: {label} {options}: compile {seconds:.1f} s, run {time.perf_counter() - started:.2f} s, "
              f"{verdict.kind}", flush=True)
