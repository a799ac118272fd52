"""stablebptt's cold start on a MuJoCo Playground env, phase by phase.

Times what the training clock of `stablebptt_half.py` counts before the first update, split into
the env's load, `env_task` (its reward diagnosis: the sampled states, then the reward's gradient),
`make_trainer` (check_task's shape trace, the initial states' resets, the memory plan and the
step's size, the jits), `init`, and the update's trace (lower) and compile. No persistent
compilation cache: every program compiles cold.

  python benchmarks/envs_vs_apg/startup.py --env CartpoleSwingup --horizon 100 --batch 8 --mode C
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import sys
import time

import jax

from stablebptt.engine import memory, training
from stablebptt.engine.config import TrainConfig, seed_array
from stablebptt.engine.training import make_trainer
from stablebptt.envs import diagnosis
from stablebptt.envs.adapter import env_task
from stablebptt.envs.protocol import load_env

TIMES: dict = {}  # wall seconds per phase
CPU: dict = {}  # CPU seconds of this process per phase (all threads): comparable on a shared machine


@contextlib.contextmanager
def timed(name):
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        yield
    finally:
        TIMES[name] = TIMES.get(name, 0.0) + time.perf_counter() - t0
        CPU[name] = CPU.get(name, 0.0) + time.process_time() - c0


def wrap(module, attribute, name):
    """Time every call of module.attribute under `name` (added up)."""
    original = getattr(module, attribute)

    def timed_call(*args, **kwargs):
        with timed(name):
            out = original(*args, **kwargs)
            if not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(out)):
                jax.block_until_ready(out)
            return out

    setattr(module, attribute, timed_call)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--env", default="CartpoleSwingup")
    p.add_argument("--horizon", type=int, default=100)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--train-batches", type=int, default=2)
    p.add_argument("--seeds", type=int, default=1)
    p.add_argument("--mode", default="C")
    p.add_argument("--out", default="", help="append the split as one JSON line to this file")
    a = p.parse_args(argv)
    jax.config.update("jax_compilation_cache_dir", None)
    jax.config.update("jax_enable_compilation_cache", False)

    for module, attribute, name in [
            (diagnosis, "diagnose_env", "env_task: diagnosis (one program)"),
            (diagnosis, "sample_for_diagnosis", "env_task: diagnosis states"),
            (diagnosis, "diagnose_reward", "env_task: diagnosis gradient"),
            (training, "check_task", "make_trainer: check_task"),
            (training, "memory_plan", "make_trainer: memory plan"),
            (training, "step_size", "make_trainer: step_size"),
            (memory, "traced_bytes", "(memory plan: traced_bytes)")]:
        if hasattr(module, attribute):
            wrap(module, attribute, name)
    t0, c0 = time.perf_counter(), time.process_time()
    with timed("env load"):
        env = load_env(a.env)
    with timed("env_task"):
        task = env_task(env, a.horizon, episode_length=1, name=a.env)
    resets = task.sample_initial_states

    def sample(key, count):
        if isinstance(key, jax.core.Tracer):  # check_task's shape trace: timed under check_task
            return resets(key, count)
        with timed("make_trainer: resets"):
            return jax.block_until_ready(resets(key, count))

    task = dataclasses.replace(task, sample_initial_states=sample)
    config = TrainConfig(mode=a.mode, batch=a.batch, train_size=a.batch * a.train_batches,
                         test_size=a.batch * a.train_batches, seeds=a.seeds, epochs=1, cosine=False,
                         epoch_program="per-update")
    with timed("make_trainer"):
        trainer = make_trainer(task, config)
    with timed("init"):
        state = jax.block_until_ready(trainer.init(seed_array(config)))
    batch = jax.tree.map(lambda x: x[0], trainer.batches)
    with timed("update: trace+lower"):
        lowered = trainer.epoch.update.lower(state, batch)
    with timed("update: compile"):
        compiled = lowered.compile()
    with timed("first update"):
        jax.block_until_ready(compiled(state, batch))
    TIMES["total to first update"] = time.perf_counter() - t0
    CPU["total to first update"] = time.process_time() - c0
    hlo = lowered.as_text()
    record = {"env": a.env, "horizon": a.horizon, "batch": a.batch, "mode": a.mode, "seeds": a.seeds,
              "backend": jax.default_backend(), "jax": jax.__version__, "argv": sys.argv,
              "update_hlo_chars": len(hlo), "seconds": {k: round(v, 2) for k, v in TIMES.items()},
              "cpu_seconds": {k: round(v, 2) for k, v in CPU.items()}}
    print(f"{'phase':34s} {'wall s':>8s} {'CPU s':>8s}")
    for k, v in TIMES.items():
        print(f"{k:34s} {v:8.2f} {CPU[k]:8.2f}")
    print(f"update module: {len(hlo)} chars of StableHLO")
    if a.out:
        os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
        with open(a.out, "a") as f:
            f.write(json.dumps(record) + "\n")


if __name__ == "__main__":
    main()
