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
from dataclasses import dataclass, field
from pathlib import Path

from stablebptt.cli import fail, parse_config
from stablebptt.apps.bench import SIMULATORS

TABLES = ("modes", "steps")

@dataclass(frozen=True)
class BenchConfig:
    tasks: str = field(default="repulsion,cartpole,quantum", metadata={"help": "comma-separated tasks"})
    poles: str = field(default="1,3", metadata={"help": "comma-separated pole counts for the cart-pole"})
    batch: int = field(default=8, metadata={"help": "initial states per update"})
    rounds: int = field(default=20, metadata={"help": "timed rounds per variant (median reported)"})
    out: str = field(default="", metadata={"help": "also write the tables to this Markdown file"})
    tables: str = field(default="modes,steps", metadata={"help": "tables to time: modes (an update per mode, every task), steps (the cart-pole's simulators against the closed-form floor, and the parts of its update)"})
    simulators: str = field(default=",".join(SIMULATORS), metadata={"help": "the cart-pole simulators of the steps table"})


def main(argv: list[str]) -> int:
    config = parse_config(BenchConfig, argv, __doc__, "benchmark")
    from stablebptt import tasks
    names = [t for t in config.tasks.split(",") if t]  # "cartpole": the MJCF task's cart-poles (--poles)
    unknown = [t for t in names if tasks.canonical(t) not in tasks.entries()]
    if unknown:
        fail(f"unknown task {unknown[0]!r}: choose from {', '.join(sorted(tasks.entries()))}")
    try:
        poles = [int(p) for p in config.poles.split(",") if p]
    except ValueError:
        fail(f"--poles takes comma-separated integers, got {config.poles!r}")
    if config.rounds <= 0 or config.batch <= 0:
        fail("--rounds and --batch must be positive")
    tables = [t for t in config.tables.split(",") if t]
    simulators = tuple(s for s in config.simulators.split(",") if s)
    for option, chosen, known in (("--tables", tables, TABLES), ("--simulators", simulators, tuple(SIMULATORS))):
        if not chosen or any(name not in known for name in chosen):
            fail(f"{option} takes a comma-separated subset of {', '.join(known)}, got {','.join(chosen) or 'nothing'}")
    import jax
    header = [f"Measured by `python scripts/bench.py {' '.join(argv)}`".rstrip()
              + f" on {platform.machine()} ({jax.devices()[0].platform}, {jax.device_count()} device, "
              f"{len(os.sched_getaffinity(0))} of {os.cpu_count()} cores), "
              f"jax {jax.__version__}, batch {config.batch}, median of {config.rounds} rounds.", ""]
    print("\n".join(header), flush=True)
    report = list(header)
    from stablebptt.apps.bench import mode_table, pipeline_table
    for name in names:
        module = tasks.load(name)
        if tasks.canonical(name) == tasks.MJCF_TASK:
            section = []
            for count in poles:
                if "modes" in tables:
                    task = module.make(module.Config(poles=count))
                    section += mode_table(f"Cart-pole (MJX), {count} pole{'s' if count > 1 else ''}", task, config.batch, config.rounds)
                if "steps" in tables:
                    section += pipeline_table(count, config.batch, config.rounds, simulators)
        elif "modes" in tables:
            section = mode_table(name.capitalize(), module.make(module.Config()), config.batch, config.rounds)
        else:
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
