"""A train.py run's update and evaluation programs (an epoch of separate programs), each traced,
compiled and run alone on this machine: seconds to trace and lower, to compile, and milliseconds per
call (the mean of five after one), with the compile cache off.

    python benchmarks/update_program.py --model S/hopper.xml --train-size 32 --test-size 8 --batch 8 --steps 50
    python benchmarks/update_program.py --flows-batched --model S/hopper.xml ...   # the reverse pass's
        # pullbacks batched over the flows (adjoint_step.pullbacks_in_turn off)

Every other option is train.py's.
"""
import os
import sys
import time

os.environ.setdefault("JAX_ENABLE_COMPILATION_CACHE", "false")

import jax  # noqa: E402

from stablebptt import tasks  # noqa: E402
from stablebptt.commands import train as train_script  # noqa: E402
from stablebptt.engine.config import seed_array  # noqa: E402
from stablebptt.engine.per_update import PerUpdateEpoch
from stablebptt.engine.training import make_trainer
from stablebptt.flows import adjoint_step

arguments = sys.argv[1:]
if "--flows-batched" in arguments:
    arguments.remove("--flows-batched")
    adjoint_step.pullbacks_in_turn = lambda: False
options, owners = train_script.parse(arguments + ["--epoch-program", "per-update"])
task_name, task_config, train_config, _, _ = train_script.configure(options, owners)
trainer = make_trainer(tasks.load(task_name).make(task_config), train_config)
assert isinstance(trainer.epoch, PerUpdateEpoch)
state = trainer.init(seed_array(train_config))
programs = (("update", trainer.epoch.update, (state, jax.tree.map(lambda a: a[0], trainer.batches))),
            ("evaluation", trainer.epoch.evaluate, (state.params, trainer.train_states, trainer.test_states)))
for name, program, inputs in programs:
    start = time.perf_counter()
    lowered = program.lower(*inputs)
    lowered_at = time.perf_counter()
    compiled = lowered.compile()
    compiled_at = time.perf_counter()
    jax.block_until_ready(compiled(*inputs))
    run_from = time.perf_counter()
    for _ in range(5):
        jax.block_until_ready(compiled(*inputs))
    print(f"{' '.join(arguments)}: {name}: trace and lower {lowered_at - start:.1f} s, compile "
          f"{compiled_at - lowered_at:.1f} s, run {(time.perf_counter() - run_from) / 5 * 1000:.1f} ms", flush=True)
