"""An environment's reward diagnosis (``diagnosis.lowered_diagnosis``, the programs a run starts with)
traced and lowered once, then compiled under each set of XLA options and run over the episodes' first
steps and along whole episodes: seconds to compile and to run, and whether every set classifies the
reward the same. The compile cache is off.

    python benchmarks/diagnosis_compile.py CartpoleSwingup [AcrobotSwingup ...]
    python benchmarks/diagnosis_compile.py --set "training's" CheetahRun   (one set of options only)
"""
import argparse
import functools
import os
import time

os.environ.setdefault("JAX_ENABLE_COMPILATION_CACHE", "false")

import jax  # noqa: E402

from stablebptt.cli import leave_out_unused_backends  # noqa: E402
from stablebptt.engine.compiling import compiler_options  # noqa: E402
from stablebptt.envs import adapter, diagnosis, protocol  # noqa: E402
from stablebptt.timing import usable_cores

leave_out_unused_backends()
# Beside an accelerator the diagnosis compiles and runs on the host's CPU (diagnosis.check_device): the CPU's sets.
ON_GPU = jax.default_backend() == "gpu" and diagnosis.check_device() is None
OPTION_SETS = {  # name -> XLA options added to the diagnosis's own (diagnosis._diagnosis_options)
    "training's": (compiler_options() if ON_GPU else None) or {},
}
if ON_GPU:
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

parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
parser.add_argument("envs", nargs="+", help="names in MuJoCo Playground's registry")
parser.add_argument("--set", action="append", choices=list(OPTION_SETS), dest="sets",
                    help="a set of XLA options to compile under, again for more (default: all)")
args = parser.parse_args()
OPTION_SETS = {label: OPTION_SETS[label] for label in args.sets or OPTION_SETS}

for name in args.envs:
    env = protocol.load_env(name)
    task = adapter.env_task(env, horizon=1, diagnose=False)
    started = time.perf_counter()
    lowered, near, whole = diagnosis.lowered_diagnosis(env, task.dynamics.step, jax.random.PRNGKey(0),
                                                       task.resolved["episode_length"])
    print(f"{name}: trace and lower {time.perf_counter() - started:.1f} s", flush=True)
    for label, options in OPTION_SETS.items():
        # Its three programs (resets, walk, checks) compile at once, each in a thread of its own, as a run's start does.
        started = time.perf_counter()
        programs = diagnosis._compiled_beside(
            [functools.partial(program.compile, compiler_options=options) for program in lowered], list).result()
        lines = " + ".join(str(program.as_text().count(chr(10))) for program in programs)
        timings = [f"compile {time.perf_counter() - started:.1f} s ({lines} lines of optimised HLO)"]
        compiled = diagnosis._Sampled(*programs)
        # Its two runs: clocks over the episodes' first steps, then (where episodes are longer) along whole ones.
        for where, arguments in (("first steps", near), ("whole episodes", whole)):
            if arguments is not None:
                started = time.perf_counter()
                verdict = diagnosis._classify(*jax.device_get(compiled(arguments)[0]))
                timings.append(f"run over {where} {time.perf_counter() - started:.2f} s ({verdict.kind})")
        print(f"{name}: {label} {options}: {', '.join(timings)}", flush=True)
