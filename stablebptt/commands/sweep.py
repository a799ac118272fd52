#!/usr/bin/env python3
"""Run a grid (task x complexity or learning rate x mode x clip mode x seeds) as few compiled programs.

    python scripts/sweep.py --preset cartpole                 # 1-4 poles x R/M/C/S x value/norm/none x 5 seeds
    python scripts/sweep.py --preset repulsion --epochs 200
    python scripts/sweep.py --preset quantum --time-limit 540 # stop and checkpoint before 9 minutes; rerun resumes
    python scripts/sweep.py --model pendulum.xml --init-pose hinge=3.14159 --horizon-seconds 7 --modes R,M,C --clips norm
    python scripts/sweep.py --env CartpoleSwingup --steps 50 --lrs 0.001,0.003 --seeds 5
    python scripts/sweep.py --preset quantum --seeds 20 --seed-range 0:5   # one piece; --merge joins the pieces

A preset varies a task's complexity; any other task (--model, --env, --task and its
options, as train.py takes them) varies the learning rate (--lrs). What shares a
program, how programs spread over devices and hosts, and what each cell leaves:
stablebptt/grids/grid.py; pieces: stablebptt/grids/pieces.py. Results land in OUT/NAME/
(NAME: the preset, or the task's name, e.g. the model file's): one run folder per
(value, mode, clip) with the seeds as rows, summary.csv, test_loss.csv, table.md,
intervals.md (C - R and C - M with 95% bootstrap intervals), verdicts.txt,
learning-curve figures, and sweeps/<time>-<values>.json per call.
"""
from __future__ import annotations

import argparse
import dataclasses
import functools
import math
import sys
import time
import typing
from dataclasses import dataclass, field
from pathlib import Path

from stablebptt import tasks
from stablebptt.cli import (
    Parser,
    add_options,
    build,
    fail,
    in_worker_thread,
    leave_out_unused_backends,
    one_line_errors,
    option_name,
    out_of_memory,
    stop_on_signals,
)
from stablebptt.commands import task_options
from stablebptt.errors import InputError
from stablebptt.reports.curves import LOSS, SCORES
from stablebptt.storage import file_sha256

# preset -> (task, the option that sets the complexity, its values): from the task registry
PRESETS = tasks.presets()


@dataclass(frozen=True)
class SweepConfig:
    preset: str = field(default="", metadata={"help": "a built-in grid over a task's complexity (default: cartpole, unless --model, --env or --task is given)", "choices": ("",) + tuple(PRESETS)})
    complexity: str = field(default="", metadata={"help": "comma-separated subset of the preset's complexities (poles, rc or target)"})
    lrs: str = field(default="", metadata={"help": "comma-separated learning rates, the grid's axis for --model, --env or --task (default: the training default, 0.001)"})
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
    report: bool = field(default=False, metadata={"help": "train nothing: rebuild summary.csv, table.md, intervals.md and figures from the run directories in OUT/NAME (without them: intervals.md from its test_loss.csv)"})
    seed_range: str = field(default="", metadata={"help": "START:STOP: train only seeds START to STOP-1 (counted from 0) of the --seeds, as a piece in OUT/NAME/pieces/ that resumes on its own (one cluster job each)"})
    merge: bool = field(default=False, metadata={"help": "train nothing: merge the pieces in OUT/NAME/pieces/ (the same command without --seed-range) into the grid's cells and report"})


def parse_list(text: str, allowed, name: str, kind=str) -> list:
    try:
        values = [kind(v) for v in text.split(",") if v.strip()]
    except ValueError:
        fail(f"--{name} takes comma-separated values, got {text!r}")
    if not values:
        fail(f"--{name} takes comma-separated values, got none in {text!r}")
    bad = [v for v in values if allowed is not None and v not in allowed]
    if bad:
        fail(f"--{name}: {bad[0]} is not one of {', '.join(map(str, allowed))}")
    twice = [v for index, v in enumerate(values) if v in values[:index]]
    if twice:  # each value is a cell of the grid: the same one twice would train it twice under one name
        fail(f"--{name} lists {twice[0]} more than once")
    return values


def hosts_given(config: SweepConfig) -> bool:
    """Whether the command names its hosts (jax.distributed's three settings); refused where it names some."""
    given = [config.coordinator != "", config.num_processes != 0, config.process_id != -1]
    if any(given) and not all(given):
        fail("--coordinator, --num-processes and --process-id go together")
    if all(given) and not (config.num_processes > 0 and 0 <= config.process_id < config.num_processes):
        fail(f"--process-id must be 0 to --num-processes - 1 ({config.num_processes - 1}), got {config.process_id}")
    return all(given)


def start_processes(config: SweepConfig, hosts: bool) -> None:
    """jax.distributed for several hosts, when asked (``hosts``: ``hosts_given``); the compilation cache."""
    import jax

    from stablebptt.runtime import use_compile_cache
    use_compile_cache(config.compile_cache)
    if hosts:
        jax.distributed.initialize(config.coordinator, config.num_processes, config.process_id)
    elif config.distributed:
        jax.distributed.initialize()


def parse(argv: list[str]) -> tuple[SweepConfig, str | None, dict]:
    """(the sweep's options, the task named by --task or implied by its options or None, the task options given)."""
    parser = Parser(description=__doc__, formatter_class=lambda prog: argparse.RawDescriptionHelpFormatter(prog, max_help_position=32))
    owners = {name: {"sweep"} for name in add_options(parser, SweepConfig, "sweep")}
    task_options.add_task_options(parser, owners)
    args = parser.parse_args(argv)
    with one_line_errors():
        config = build(SweepConfig, vars(args))
    given = task_options.task_options_given(args, owners, "sweep")
    if config.preset:
        task_name = PRESETS[config.preset][0]
        if args.task is not None and tasks.canonical(args.task) != task_name:
            fail(f"--preset {config.preset} is a grid of --task {task_name}, not of --task {args.task}")
        args.task = task_name  # the preset's task takes the options given
    custom = args.task is not None or bool(given)
    task_name = task_options.choose_task(args, owners, "sweep") if custom else None
    return config, task_name, given


class Plan(typing.NamedTuple):
    """What a sweep call varies and where its cells go."""

    task_name: str
    option: str  # the axis: a task option (a preset's complexity) or a training option ("lr")
    values: list
    train_option: str  # "lr" when the axis is a training option, else ""
    make_task: typing.Callable
    task_config: typing.Callable
    name: str  # OUT/NAME
    score: tuple[str, float]  # how the report reads the test loss


def plan_grid(config: SweepConfig, task_name: str | None, given: dict) -> Plan:
    """The grid's axis and task from the options: a preset's complexities, or learning rates of any task."""
    if config.task_steps and "steps" in given:
        fail("--task-steps and --steps set the same horizon: give one")
    if config.task_steps:
        given = {**given, "steps": config.task_steps}
    preset = config.preset or ("" if task_name else "cartpole")
    if preset:
        task_name, option, complexities = PRESETS[preset]
        if option in given:
            fail(f"{option_name(option)} is the axis of --preset {preset}: choose its values with --complexity")
        if config.lrs:
            fail(f"--lrs is the axis of a grid over --model, --env or --task; --preset {preset} varies {option_name(option)}")
        values = parse_list(config.complexity, complexities, "complexity", type(complexities[0])) if config.complexity else list(complexities)
        build_config = lambda value: task_options.task_config(task_name, {**given, option: value})
        # Built once per value: planning, each program and each cell's record ask for it.
        make_task = functools.lru_cache(maxsize=None)(lambda value: tasks.load(task_name).make(build_config(value)))
        return Plan(task_name, option, values, "", make_task, build_config, preset, SCORES.get(task_name, LOSS))
    if config.complexity:
        fail("--complexity chooses among a preset's complexities; a grid over --model, --env or --task varies --lrs")
    from stablebptt.engine.config import TrainConfig
    values = parse_list(config.lrs, None, "lrs", float) if config.lrs else [TrainConfig.lr]
    if not all(math.isfinite(v) and v > 0 for v in values):
        fail(f"--lrs takes positive learning rates, got {config.lrs}")
    with one_line_errors():
        fixed = task_options.task_config(task_name, given)
        from stablebptt.engine.checks import check_options
        check_options(TrainConfig(), fixed)  # task options that make each other meaningless
        task = tasks.load(task_name).make(fixed)  # built once: the learning rate does not change it
    return Plan(task_name, "lr", values, "lr", lambda value: task, lambda value: fixed, task.name,
                SCORES.get(task_name, LOSS))


def model_contents(task_configs: list) -> list | None:
    """Per axis value, the SHA-256 of the model file the task reads (an MJCF task's ``model_path``), as
    ``train --resume`` checks a run's; None where no value has one. A grid records it, so that a grid,
    a piece or a merge refuses a model file whose contents changed."""
    paths = [getattr(task_config, "model_path", None) for task_config in task_configs]
    if not any(paths):
        return None
    digests = {path: file_sha256(path) for path in set(paths) if path and Path(path).is_file()}  # each file read once
    return [digests.get(path) for path in paths]




def main(argv: list[str]) -> int:
    leave_out_unused_backends()  # before parsing, which imports the tasks and MJX with them
    config, task_name, given = parse(argv)
    from stablebptt.engine.config import CLIP_MODES
    from stablebptt.flows.modes import MODES
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
    if config.seed_range and (config.merge or config.report):
        fail("--seed-range trains a piece; --merge and --report train nothing: give one")
    if config.merge and config.report:
        fail("--merge reports too, from the pieces it merges: give --merge, or --report alone")
    hosts = hosts_given(config)  # before the task is built
    from stablebptt.grids.pieces import parse_seed_range
    with one_line_errors():
        start, stop = parse_seed_range(config.seed_range, config.seeds) if config.seed_range else (0, config.seeds)
    plan = plan_grid(config, task_name, given)
    root = Path(config.out) / plan.name
    from stablebptt.grids import grid as grids
    from stablebptt.grids import pieces as grid_pieces
    from stablebptt.grids import report as grid_report

    identity = {"task_steps": config.task_steps, **({"task_options": given} if given else {})}
    if (inputs := model_contents([plan.task_config(value) for value in plan.values])) is not None:
        identity["inputs"] = inputs
    grid = grids.Grid(
        plan.task_name, plan.option, tuple(plan.values), make_task=plan.make_task, task_config=plan.task_config,
        modes=tuple(modes), clips=tuple(clips), seeds=tuple(FIRST_SEED + s for s in range(start, stop)),
        epochs=config.epochs, train_size=config.train_size, test_size=config.test_size,
        checkpoint_every=config.checkpoint_every, checkpoint_seconds=config.checkpoint_seconds, unroll=config.unroll,
        gpu_unroll=tasks.entry(plan.task_name).gpu_unroll, group_values=config.group_values, name=plan.name,
        identity=identity, train_option=plan.train_option)
    report = lambda: grid_report.write_report(root, grid_report.run_directories(root, plan.task_name, plan.option),
                                              plan.task_name, plan.option, plan.values, modes, clips, plan.score)

    if config.report:
        directories = grid_report.run_directories(root, plan.task_name, plan.option)
        if not directories and (root / "test_loss.csv").is_file():  # only the tidy CSV ships in results/
            print("\n".join(grid_report.write_intervals(root, plan.option)))
            return 0
        if not directories:
            fail(f"no run directories of {plan.name} in {root}")
        print("\n".join(report()))
        return 0
    if config.merge:
        with one_line_errors():
            merged = merge(grid, grids, root, config.seeds)
        print("\n".join(report()))
        print(f"merged {merged} pieces into {root}")
        return 0

    start_processes(config, hosts)
    import jax
    from tqdm import tqdm
    where = grid_pieces.piece_root(root, start, stop) if config.seed_range else root
    where.mkdir(parents=True, exist_ok=True)
    lock = None
    if jax.process_count() == 1:  # the processes of one distributed grid share its folder; another grid may not
        from stablebptt.runs.run_folder import RunLock
        with one_line_errors():
            lock = RunLock(where)
    try:
        if config.seed_range:
            with one_line_errors():
                grid_pieces.write_manifest(where, grids.describe(grid, FIRST_SEED, config.seeds),
                                           start, stop)
        wall = time.perf_counter()
        deadline = time.monotonic() + config.time_limit if config.time_limit else None
        log = lambda message: tqdm.write(message, file=sys.stderr)
        # A signal (Ctrl-C, SIGTERM, SIGHUP) sets a flag, as in train.py: every program checkpoints
        # after its current epoch and stops.
        with stop_on_signals(log) as interrupted:
            try:
                stop_now = lambda: interrupted() or (deadline is not None and time.monotonic() > deadline)
                outcome = in_worker_thread(lambda: grids.run_grid(grid, where, stop_now, log))
            except InputError as error:
                fail(str(error))
            except jax.errors.JaxRuntimeError as error:
                if (line := out_of_memory(error)) is None:
                    raise
                fail(f"{line}; every program keeps its last checkpoint: free memory (another process may hold it) and "
                     f"run the same command again to resume, or give fewer --seeds", code=1)
        if interrupted():
            print("interrupted: the programs checkpointed; run the same command again to resume", file=sys.stderr)
            return interrupted.exit_code
        finished = all(r["epochs_done"] == config.epochs for r in outcome)
        record = grids.write_record(where, {"preset": plan.name, "option": plan.option,
                                            "config": dataclasses.asdict(config), "finished": finished,
                                            "wall_seconds_this_call": time.perf_counter() - wall}, outcome)
        if jax.process_index() == 0 and not config.seed_range:
            # The report covers every run directory of the grid, also those of earlier or parallel calls.
            print("\n".join(report()))
        if config.seed_range:
            print(f"{'done' if finished else 'stopped at the time limit; run again to resume'}: piece {where} "
                  f"(record: {record.name}); once every piece is done, the same command with --merge instead of "
                  f"--seed-range joins them")
        else:
            print(f"{'done' if finished else 'stopped at the time limit; run again to resume'}: {root} "
                  f"(record: {record.name})")
        return 0
    finally:
        if lock is not None:
            lock.release()


FIRST_SEED = 42  # the grid's seeds are FIRST_SEED, FIRST_SEED + 1, ...


def merge(grid, grids, root: Path, seeds: int) -> int:
    """The pieces under ``root`` -> the grid's cells in ``root``; returns how many pieces were merged."""
    from stablebptt.grids import pieces as grid_pieces
    from stablebptt.grids import report as grid_report
    from stablebptt.runs import model_store
    whole = dataclasses.replace(grid, seeds=tuple(FIRST_SEED + s for s in range(seeds)))
    names = [grid_report.cell_name(grid.task_name, grid.option, value, mode, clip)
             for value in grid.values for mode in grid.modes for clip in grid.clips]
    folders = grid_pieces.check_pieces(root, grids.describe(grid, FIRST_SEED, seeds), names)
    grids.check_cells_are_this_grids(grids.plan(whole, root), whole, root)
    shared = model_store.SharedModels(root)  # each model compiled and kept once for all the cells
    for name in names:
        grid_pieces.merge_cell(folders, name, root, grids.write_cell, shared)
    return len(folders)


if __name__ == "__main__":
    from stablebptt.cli import stop_at_once_on_signals
    stop_at_once_on_signals()
    sys.exit(main(sys.argv[1:]))
