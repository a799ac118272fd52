#!/usr/bin/env python3
"""Run a grid (task x complexity x mode x clip mode x seeds) as few compiled programs, side by side on the devices.

    python scripts/sweep.py --preset cartpole                 # 1-4 poles x R/M/C/S x value/norm/none x 5 seeds
    python scripts/sweep.py --preset repulsion --epochs 200
    python scripts/sweep.py --preset quantum --time-limit 540 # stop and checkpoint before 9 minutes; rerun resumes

What shares a program, how programs spread over devices and hosts, and what each cell
leaves: stablebptt/grid.py. Results land in OUT/PRESET/: one run folder per (complexity,
mode, clip) with the seeds as rows, summary.csv, test_loss.csv, table.md, learning-curve
figures, and sweeps/<time>-<complexities>.json per call with wall times and devices.
"""
from __future__ import annotations

import dataclasses
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from stablebptt import tasks
from stablebptt.cli import build, fail, in_worker_thread, out_of_memory, parse_config, stop_on_signals
from stablebptt.errors import InputError

# preset -> (task, the option that sets the complexity, its values): from the task registry
PRESETS = tasks.presets()


@dataclass(frozen=True)
class SweepConfig:
    preset: str = field(default="cartpole", metadata={"help": "which grid", "choices": tuple(PRESETS)})
    complexity: str = field(default="", metadata={"help": "comma-separated subset of the preset's complexities (poles, rc or target)"})
    modes: str = field(default="R,M,C,S", metadata={"help": "comma-separated gradient flows"})
    clips: str = field(default="value,norm,none", metadata={"help": "comma-separated clip modes"})
    seeds: int = field(default=5, metadata={"help": "seeds per cell (the same seeds in every cell)"})
    epochs: int = field(default=1000, metadata={"help": "epochs per cell"})
    train_size: int = field(default=256, metadata={"help": "training initial states"})
    test_size: int = field(default=256, metadata={"help": "test initial states"})
    task_steps: int = field(default=0, metadata={"help": "override the task's horizon in steps (0: its own; for quick tests)"})
    unroll: int = field(default=0, metadata={"help": "rollout steps per loop iteration (0: measured per-task value on GPUs, 1 on CPUs)"})
    checkpoint_every: int = field(default=10, metadata={"help": "epochs between checkpoints and progress lines"})
    checkpoint_seconds: float = field(default=30.0, metadata={"help": "and at least this many seconds between checkpoints (a stop and the end always save)"})
    time_limit: float = field(default=0.0, metadata={"help": "seconds after which to checkpoint and stop (0: none); rerun to resume"})
    out: str = field(default="results", metadata={"help": "results root; the sweep writes OUT/PRESET/"})
    distributed: bool = field(default=False, metadata={"help": "several hosts: jax.distributed, its settings from the cluster (Slurm, Open MPI, ...) or JAX_COORDINATOR_ADDRESS"})
    coordinator: str = field(default="", metadata={"help": "several hosts: HOST:PORT of process 0 (with --num-processes and --process-id)"})
    num_processes: int = field(default=0, metadata={"help": "several hosts: how many processes take part"})
    process_id: int = field(default=-1, metadata={"help": "several hosts: this process's number, 0 to --num-processes - 1"})
    group_values: bool = field(default=True, metadata={"help": "vmap a task's complexities into one program where it can (fewer compiles); --no-group-values: a program each, to spread over devices or hosts"})
    compile_cache: bool = field(default=True, metadata={"help": "keep compiled programs between calls (in $STABLEBPTT_COMPILE_CACHE or ~/.cache/stablebptt)"})
    report: bool = field(default=False, metadata={"help": "train nothing: rebuild summary.csv, table.md, intervals.md and figures from the run directories in OUT/PRESET (without them: intervals.md from its test_loss.csv)"})


def parse_list(text: str, allowed, name: str, kind=str) -> list:
    try:
        values = [kind(v) for v in text.split(",") if v.strip()]
    except ValueError:
        fail(f"--{name} takes comma-separated values, got {text!r}")
    bad = [v for v in values if v not in allowed]
    if bad or not values:
        fail(f"--{name}: {bad[0] if bad else 'nothing'} is not one of {', '.join(map(str, allowed))}")
    return values


def task_config(task_name: str, option: str, value, config: SweepConfig):
    task_options = {option: value}
    if config.task_steps:
        task_options["steps"] = config.task_steps
    return build(tasks.load(task_name).Config, task_options)


def start_processes(config: SweepConfig) -> None:
    """jax.distributed for several hosts, when asked; the compilation cache."""
    given = [config.coordinator != "", config.num_processes != 0, config.process_id != -1]
    if any(given) and not all(given):
        fail("--coordinator, --num-processes and --process-id go together")
    if all(given) and not (config.num_processes > 0 and 0 <= config.process_id < config.num_processes):
        fail(f"--process-id must be 0 to --num-processes - 1 ({config.num_processes - 1}), got {config.process_id}")
    import jax
    from stablebptt.cli import use_compile_cache
    use_compile_cache(config.compile_cache)
    if all(given):
        jax.distributed.initialize(config.coordinator, config.num_processes, config.process_id)
    elif config.distributed:
        jax.distributed.initialize()


def main(argv: list[str]) -> int:
    config = parse_config(SweepConfig, argv, __doc__, "sweep")
    task_name, option, complexities = PRESETS[config.preset]
    if config.complexity:
        complexities = parse_list(config.complexity, complexities, "complexity", type(complexities[0]))
    from stablebptt.training import CLIP_MODES, MODES
    modes = parse_list(config.modes, MODES, "modes")
    clips = parse_list(config.clips, CLIP_MODES, "clips")
    if config.unroll < 0:
        fail("--unroll must be 0 (automatic) or a positive integer")
    for name in ("seeds", "epochs", "train_size", "test_size", "checkpoint_every"):
        if getattr(config, name) <= 0:
            fail(f"--{name.replace('_', '-')} must be a positive integer")
    for name in ("checkpoint_seconds", "time_limit"):
        if not (math.isfinite(getattr(config, name)) and getattr(config, name) >= 0):
            fail(f"--{name.replace('_', '-')} must be a number of seconds, 0 or more, got {getattr(config, name)}")
    root = Path(config.out) / config.preset
    from stablebptt import grid as grids

    if config.report:
        directories = grids.run_directories(root, task_name, option)
        if not directories and (root / "test_loss.csv").is_file():  # only the tidy CSV ships in results/
            print("\n".join(grids.write_intervals(root, option)))
            return 0
        if not directories:
            fail(f"no run directories of preset {config.preset} in {root}")
        print("\n".join(grids.write_report(root, directories, task_name, option, complexities, modes, clips)))
        return 0

    start_processes(config)
    import jax
    from tqdm import tqdm
    root.mkdir(parents=True, exist_ok=True)
    grid = grids.Grid(
        task_name, option, tuple(complexities),
        make_task=lambda value: tasks.load(task_name).make(task_config(task_name, option, value, config)),
        task_config=lambda value: task_config(task_name, option, value, config),
        modes=tuple(modes), clips=tuple(clips), seeds=tuple(42 + s for s in range(config.seeds)),
        epochs=config.epochs, train_size=config.train_size, test_size=config.test_size,
        checkpoint_every=config.checkpoint_every, checkpoint_seconds=config.checkpoint_seconds, unroll=config.unroll, gpu_unroll=tasks.entry(task_name).gpu_unroll,
        group_values=config.group_values, name=config.preset, identity={"task_steps": config.task_steps})
    wall = time.perf_counter()
    deadline = time.monotonic() + config.time_limit if config.time_limit else None
    log = lambda message: tqdm.write(message, file=sys.stderr)
    # A signal (Ctrl-C, SIGTERM, SIGHUP) sets a flag, as in train.py: every program checkpoints
    # after its current epoch and stops.
    with stop_on_signals(log) as interrupted:
        try:
            stop = lambda: interrupted() or (deadline is not None and time.monotonic() > deadline)
            report = in_worker_thread(lambda: grids.run_grid(grid, root, stop, log))
        except InputError as error:
            fail(str(error))
        except jax.errors.JaxRuntimeError as error:
            if (line := out_of_memory(error)) is None:
                raise
            fail(f"{line}; every program keeps its last checkpoint: free memory (another process may hold it) and "
                 f"run the same command again to resume, or give fewer --seeds", code=1)
    if interrupted():
        print("interrupted: the programs checkpointed; run the same command again to resume", file=sys.stderr)
        return 130
    finished = all(r["epochs_done"] == config.epochs for r in report)
    record = grids.write_record(root, {"preset": config.preset, "option": option, "config": dataclasses.asdict(config),
                                       "finished": finished, "wall_seconds_this_call": time.perf_counter() - wall}, report)
    if jax.process_index() == 0:
        # The report covers every run directory of the preset, also those of earlier or parallel calls.
        print("\n".join(grids.write_report(root, grids.run_directories(root, task_name, option), task_name, option,
                                            PRESETS[config.preset][2], modes, clips)))
    print(f"{'done' if finished else 'stopped at the time limit; run again to resume'}: {root} (record: {record.name})")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
