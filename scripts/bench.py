#!/usr/bin/env python3
"""Measure update times, in one run, and print them as Markdown tables.

    python scripts/bench.py                          # every task, poles 1 and 3
    python scripts/bench.py --tasks cartpole --poles 1,2,3,4 --out results/bench_cpu.md
    python scripts/bench.py --tasks cartpole --tables steps --simulators generated,floor   # the floor ratio alone

Per task, one update (gradient of a batch-8 rollout, then clip and Adam) per mode:
R, M, S and C through the one-pass flows, and "R plain": jax.grad of the plain
rollout with no flow machinery, the baseline the ratios divide by. For the
cart-pole, also its steps: the default one generated body by body (stablebptt/tree.py),
MJX's stages the scene needs (differentiated through inverse dynamics), the same
differentiated by plain autodiff through the mass matrix and its solve, the same
with MJX's dense mass matrix, mjx.step with MuJoCo's default flags, and
closed-form cart-pole equations as the floor; and the parts of the default R update (the rollout alone, and every step's
Jacobian built in one batched call, as the update builds them). Variants of one table are timed round-robin, so drift of
the machine hits all of them alike; tables are timed one after another.
"""
from __future__ import annotations

import os
import platform
import sys
from pathlib import Path

from stablebptt.apps.bench import TABLES, BenchConfig
from stablebptt.cli import fail, parse_config
from stablebptt.errors import InputError


def main(argv: list[str]) -> int:
    config = parse_config(BenchConfig, argv, __doc__, "benchmark")
    from stablebptt import tasks
    names = config.task_list  # "cartpole": the MJCF task's cart-poles (--poles)
    unknown = [t for t in names if tasks.canonical(t) not in tasks.entries()]
    if unknown:
        fail(f"unknown task {unknown[0]!r}: choose from {', '.join(sorted(tasks.entries()))}")
    if config.rounds <= 0 or config.batch <= 0:
        fail("--rounds and --batch must be positive")
    tables = config.table_list
    if not tables or any(name not in TABLES for name in tables):
        fail(f"--tables takes a comma-separated subset of {', '.join(TABLES)}, got {','.join(tables) or 'nothing'}")
    from stablebptt.apps.bench import bench_cases, mode_table
    try:  # every task's cases before anything is timed: a bad option is refused at once
        cases = {name: bench_cases(name, config) for name in names}
    except InputError as error:
        fail(str(error))
    import jax
    header = [f"Measured by `python scripts/bench.py {' '.join(argv)}`".rstrip()
              + f" on {platform.machine()} ({jax.devices()[0].platform}, {jax.device_count()} device, "
              f"{len(os.sched_getaffinity(0))} of {os.cpu_count()} cores), "
              f"jax {jax.__version__}, batch {config.batch}, median of {config.rounds} rounds.", ""]
    print("\n".join(header), flush=True)
    report = list(header)
    for name in names:
        module = tasks.load(name)
        section = []
        for case in cases[name]:
            if "modes" in tables:
                section += mode_table(case.title, module.make(case.task_config), config.batch, config.rounds)
            if "steps" in tables and case.steps is not None:
                section += case.steps()
        if not section:
            continue
        print("\n".join(section), flush=True)
        report += section
        if config.out:  # after every task, so a long benchmark keeps what it measured
            from stablebptt.storage import atomic_write
            Path(config.out).parent.mkdir(parents=True, exist_ok=True)
            atomic_write(Path(config.out), ("\n".join(report) + "\n").encode())
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
