#!/usr/bin/env python3
"""Run a grid (task x complexity x mode x clip mode x seeds) as few compiled programs, side by side on the devices.

    python scripts/sweep.py --preset cartpole                 # 1-4 poles x R/M/C/S x value/norm/none x 5 seeds
    python scripts/sweep.py --preset repulsion --epochs 200
    python scripts/sweep.py --preset quantum --time-limit 540 # stop and checkpoint before 9 minutes; rerun resumes

Everything that does not change the compiled program is vmapped into one
program: seeds, mode (each cell computes R, M and S and its mode selects), clip
mode and threshold, learning rate, and a task option that enters only the loss
(repulsion's rc, quantum's target: one program for the whole grid). Cart-pole's
poles change the model, so each pole count is its own program. Programs spread
over every visible device: each takes a group of devices and runs beside the
others, its cells sharded over its group (jax.sharding); with --distributed,
jax.distributed spans several hosts and each host runs the groups of its own
devices. On an H200 a program is bound by kernel latency (240 cells cost 1.2x
of 60), so a GPU per program is what halves the time, not more GPUs per program.
Results land in OUT/PRESET/: one run directory per (complexity, mode, clip)
with the seeds as rows (scripts/plot.py reads them), summary.csv with the final
test loss per cell, test_loss.csv (every seed's test loss every 10 epochs),
learning-curve figures, and sweeps/<time>-<complexities>.json per call with
wall times and devices.
"""
from __future__ import annotations

import sys
from pathlib import Path


import dataclasses
import itertools
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import wait as futures_wait
from dataclasses import dataclass, field
from typing import Callable

from stablebptt.cli import build, fail, parse_config, stop_on_signals
from stablebptt.errors import InputError

# preset -> (task, the option that sets the complexity, its values)
PRESETS = {
    "cartpole": ("cartpole", "poles", (1, 2, 3, 4)),
    "repulsion": ("repulsion", "rc", (1.0, 0.1, 0.01, 0.001)),
    "quantum": ("quantum", "target", (3, 4, 5)),
    "tiny": ("repulsion", "rc", (1.0, 0.1)),  # the CPU test of the machinery
}
# Rollout-loop unrolling on GPUs: the README's GPU table gives the measured s/epoch (one H200,
# 60 cells); beyond these counts compile time grows faster than the gain.
GPU_UNROLL = {"cartpole": 5, "quantum": 8, "repulsion": 10}


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
    checkpoint_every: int = field(default=10, metadata={"help": "epochs between checkpoints"})
    time_limit: float = field(default=0.0, metadata={"help": "seconds after which to checkpoint and stop (0: none); rerun to resume"})
    out: str = field(default="results", metadata={"help": "results root; the sweep writes OUT/PRESET/"})
    distributed: bool = field(default=False, metadata={"help": "call jax.distributed.initialize() (several hosts)"})
    report: bool = field(default=False, metadata={"help": "train nothing: rebuild summary.csv, table.md and figures from the run directories in OUT/PRESET"})


@dataclass
class Program:
    """One compiled program: one or more complexities of the grid, all their cells vmapped."""

    values: list  # the complexities this program trains
    cells: list  # (value, mode, clip, seed) per cell
    directory: Path


def plan_programs(values, modes, clips, seeds, per_cell: bool, option: str, root: Path) -> list[Program]:
    """One program for all values where the task takes them per cell, else one per value."""
    groups = [list(values)] if per_cell else [[value] for value in values]
    return [Program(group, [(v, m, c, s) for v, m, c, s in itertools.product(group, modes, clips, seeds)],
                    root / "_programs" / f"{option}{'_'.join(map(str, group))}") for group in groups]


def place(programs: list, devices: list, process_index: int = 0) -> list[tuple[list, list]]:
    """Split the devices into groups, one program per group at a time: [(devices, programs)].

    With more devices than programs each program gets a group of several
    (its cells sharded over them); with fewer, programs queue on the groups.
    A group never spans processes, and only this process's groups are
    returned: under jax.distributed each host runs the programs placed on
    its own devices.
    """
    by_process = {}
    for device in devices:
        by_process.setdefault(device.process_index, []).append(device)
    hosts = list(by_process.values())
    # Give every host the same number of groups, as many as programs allow.
    per_host = max(1, min(len(hosts[0]), -(-len(programs) // len(hosts))))
    groups = []
    for host in hosts:
        bounds = [len(host) * i // per_host for i in range(per_host + 1)]  # sizes differ by one at most
        groups += [host[bounds[i]:bounds[i + 1]] for i in range(per_host)]
    queues = [(group, programs[i::len(groups)]) for i, group in enumerate(groups)]
    return [(group, queue) for group, queue in queues if queue and group[0].process_index == process_index]


def parse_list(text: str, allowed, name: str, kind=str) -> list:
    try:
        values = [kind(v) for v in text.split(",") if v.strip()]
    except ValueError:
        fail(f"--{name} takes comma-separated values, got {text!r}")
    bad = [v for v in values if v not in allowed]
    if bad or not values:
        fail(f"--{name}: {bad[0] if bad else 'nothing'} is not one of {', '.join(map(str, allowed))}")
    return values


def cell_name(task_name, option, value, mode, clip) -> str:
    return f"{task_name}-{option}{value}-{mode}-{clip}"


def make_task(task_name: str, option: str, value, config: SweepConfig):
    from stablebptt import tasks
    module = tasks.load(task_name)
    task_options = {option: value}
    if config.task_steps:
        task_options["steps"] = config.task_steps
    return module.make(build(module.Config, task_options))


def takes_per_cell(task, option: str) -> bool:
    return task.cell_option is not None and task.cell_option.name == option


def identity(program: Program, task_name: str, option: str, config: SweepConfig) -> dict:
    """What a program's checkpoint belongs to; a resume must match it."""
    return {"cells": [list(c) for c in program.cells], "task": task_name, option: program.values,
            "train_size": config.train_size, "test_size": config.test_size, "task_steps": config.task_steps}


def check_resumable(program: Program, task_name: str, option: str, config: SweepConfig) -> None:
    from stablebptt import runs
    identity_file = program.directory / "cells.json"
    if identity_file.exists() and runs.read_json(identity_file) != identity(program, task_name, option, config):
        raise InputError(f"{program.directory} holds a checkpoint of a different grid: choose another --out or remove it")


def run_program(program: Program, task_name: str, option: str, config: SweepConfig, devices: list, log,
                should_stop: Callable[[], bool]) -> dict:
    """Train every cell of one program on its devices to config.epochs, resuming from its checkpoint.

    ``should_stop()`` true (time limit, or another program failed) checkpoints and returns early.
    """
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec
    from stablebptt import runs
    from stablebptt.training import CLIP_MODES, MODES, TrainConfig, make_trainer

    task = make_task(task_name, option, program.values[0], config)
    per_cell = takes_per_cell(task, option)
    unroll = config.unroll or (GPU_UNROLL.get(task_name, 1) if devices[0].platform == "gpu" else 1)
    count = len(program.cells)
    cells = program.cells + [program.cells[-1]] * (-count % len(devices))  # pad to a multiple of the devices
    train_config = TrainConfig(epochs=config.epochs, seeds=len(cells), train_size=config.train_size,
                               test_size=config.test_size, seed_batching="vmap", checkpoint_every=config.checkpoint_every,
                               unroll=unroll)
    trainer = make_trainer(task, train_config, grid=True)
    sharding = NamedSharding(Mesh(np.array(devices), ("cells",)), PartitionSpec("cells"))
    shard = lambda tree: jax.device_put(tree, sharding)

    seeds = jnp.array([seed for _, _, _, seed in cells], dtype=jnp.uint32)
    state = trainer.init(seeds)
    hyper = dict(state.opt_state.hyperparams)
    hyper["mode_index"] = jnp.array([MODES.index(mode) for _, mode, _, _ in cells], dtype=hyper["mode_index"].dtype)
    hyper["clip_index"] = jnp.array([CLIP_MODES.index(clip) for _, _, clip, _ in cells], dtype=hyper["clip_index"].dtype)
    state = state._replace(opt_state=state.opt_state._replace(hyperparams=hyper))
    program.directory.mkdir(parents=True, exist_ok=True)
    runs.write_json(program.directory / "cells.json", identity(program, task_name, option, config))
    # Checkpoints hold the real cells only, so a program resumes on any number of devices.
    unpad = lambda tree: jax.tree.map(lambda a: a[:count], tree)
    if (program.directory / runs.CHECKPOINT_FILE).exists():
        start, loaded, rows = runs.load_checkpoint(program.directory, unpad(state))
        state = jax.tree.map(lambda fresh, saved: fresh.at[:count].set(saved), state, loaded)
    else:
        start, rows = 0, runs.empty_rows()
    state = shard(state)
    values = shard(jnp.asarray([value for value, _, _, _ in cells])) if per_cell else None
    arguments = (values, trainer.batches, trainer.train_states, trainer.test_states)
    started = time.perf_counter()
    epoch_fn = trainer.epoch.lower(state, *arguments).compile()
    compile_seconds = time.perf_counter() - started
    cell_index = np.arange(count)

    def run_epoch(state):
        state, metrics = epoch_fn(state, *arguments)
        # A diverged cell keeps its NaNs in the table; vmapped cells cannot affect each other.
        return state, unpad(jax.device_get(metrics))

    def save(epoch, state, rows):
        runs.save_checkpoint(program.directory, epoch, unpad(state), rows)
        log(f"{task_name} {option}={','.join(map(str, program.values))}: epoch {epoch}/{config.epochs}, "
            f"{(time.perf_counter() - started - compile_seconds) / max(epoch - start, 1):.2f} s/epoch for {count} cells "
            f"on {len(devices)} device(s)")

    _, epoch, state, rows, _ = runs.fit(run_epoch, state, start, config.epochs, rows, cell_index, save,
                                        config.checkpoint_every, should_stop)
    return {"complexity": program.values, "epochs_done": int(epoch), "cells": count, "unroll": unroll,
            "devices": [str(d) for d in devices], "padded_cells": len(cells), "compile_seconds": compile_seconds,
            "train_seconds": time.perf_counter() - started - compile_seconds, "rows": rows}


def write_cells(program: Program, rows, task_name: str, option: str, config: SweepConfig, root: Path) -> None:
    """Split a program's rows into one run directory per (mode, clip), seeds as rows."""
    import numpy as np
    from stablebptt import runs
    groups = {}
    for index, (value, mode, clip, seed) in enumerate(program.cells):
        groups.setdefault((value, mode, clip), []).append((index, seed))
    for (value, mode, clip), members in groups.items():
        directory = root / cell_name(task_name, option, value, mode, clip)
        directory.mkdir(parents=True, exist_ok=True)
        selected = []
        for index, seed in members:
            part = rows[rows[:, 1] == index].copy()
            part[:, 1] = seed
            selected.append(part)
        table = np.concatenate(selected)
        table = table[np.lexsort((table[:, 1], table[:, 0]))]
        runs.write_json(directory / runs.CONFIG_FILE, {
            "task": task_name, "task_config": {option: value},
            "train": {"mode": mode, "clip": clip, "seeds": len(members), "seed": members[0][1], "epochs": config.epochs,
                      "train_size": config.train_size, "test_size": config.test_size},
            "sweep": config.preset})
        runs.write_metrics(directory / runs.METRICS_FILE, table)


def summarize(root: Path, directories: list[Path]) -> list[str]:
    """summary.csv and a Markdown table: final test loss, mean +- std over seeds, per cell."""
    import numpy as np
    from stablebptt import runs
    lines = ["| cell | epochs | final test loss (mean +- std over seeds) | diverged seeds |", "|---|---:|---:|---:|"]
    csv_lines = ["cell,epochs,test_loss_mean,test_loss_std,diverged_seeds"]
    for directory in sorted(directories):
        rows = runs.read_metrics(directory / runs.METRICS_FILE)
        last = max(row["epoch"] for row in rows)
        final = np.array([row["test_loss"] for row in rows if row["epoch"] == last])
        diverged = int(np.sum(~np.isfinite(final)))
        finite = final[np.isfinite(final)]
        mean, std = (float(finite.mean()), float(finite.std())) if len(finite) else (float("nan"), float("nan"))
        lines.append(f"| {directory.name} | {int(last)} | {mean:.4g} +- {std:.2g} | {diverged} |")
        csv_lines.append(f"{directory.name},{int(last)},{mean!r},{std!r},{diverged}")
    runs.atomic_write(root / "summary.csv", ("\n".join(csv_lines) + "\n").encode())
    return lines


def mode_table(directories: list[Path], task_name: str, option: str, complexities, modes, clips) -> list[str]:
    """Final test loss, mean +- std over seeds: one row per complexity and clip mode, one column per mode."""
    import numpy as np
    from stablebptt import runs
    lines = [f"| {option} | clip | epochs | " + " | ".join(modes) + " |", "|---|---|---:|" + "---:|" * len(modes)]
    for value in complexities:
        for clip in clips:
            cells, epochs = [], ""
            for mode in modes:
                directory = next((d for d in directories if d.name == cell_name(task_name, option, value, mode, clip)), None)
                if directory is None:
                    cells.append("-")
                    continue
                rows = runs.read_metrics(directory / runs.METRICS_FILE)
                last = max(r["epoch"] for r in rows)
                final = np.array([r["test_loss"] for r in rows if r["epoch"] == last])
                epochs = str(int(last))
                cells.append(f"{np.nanmean(final):.3g} +- {np.nanstd(final):.2g}" if np.isfinite(final).any() else "diverged")
            lines.append(f"| {value} | {clip} | {epochs} | " + " | ".join(cells) + " |")
    return lines


def tidy_test_loss(root: Path, directories: list[Path], option: str, every: int = 10) -> None:
    """test_loss.csv: one row per cell, seed and every tenth epoch (and the last), small enough for git."""
    from stablebptt import runs
    lines = [f"{option},mode,clip,seed,epoch,test_loss"]
    for directory in sorted(directories):
        config = runs.read_json(directory / runs.CONFIG_FILE)
        value, train = config["task_config"][option], config["train"]
        rows = runs.read_metrics(directory / runs.METRICS_FILE)
        last = max(row["epoch"] for row in rows)
        lines += [f"{value},{train['mode']},{train['clip']},{int(row['seed'])},{int(row['epoch'])},{row['test_loss']:.7g}"
                  for row in rows if row["epoch"] % every == 0 or row["epoch"] == last]
    runs.atomic_write(root / "test_loss.csv", ("\n".join(lines) + "\n").encode())


def write_report(root: Path, directories: list[Path], task_name, option, complexities, modes, clips) -> None:
    """summary.csv, test_loss.csv, table.md and one learning-curve figure per complexity, from the run directories."""
    from stablebptt.plots import learning_curves
    from stablebptt.runs import atomic_write
    summarize(root, directories)
    tidy_test_loss(root, directories, option)
    table = mode_table(directories, task_name, option, complexities, modes, clips)
    atomic_write(root / "table.md", ("\n".join(table) + "\n").encode())
    for value in complexities:
        members = [d for d in directories if d.name.startswith(f"{task_name}-{option}{value}-")]
        if members:
            learning_curves(members, root / f"{task_name}-{option}{value}.png", smooth=None)
    print("\n".join(table))


def run_directories(root: Path, task_name: str, option: str) -> list[Path]:
    from stablebptt import runs
    return sorted(d for d in root.glob(f"{task_name}-{option}*") if (d / runs.METRICS_FILE).exists())


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

    if config.report:
        root = Path(config.out) / config.preset
        directories = run_directories(root, task_name, option)
        if not directories:
            fail(f"no run directories of preset {config.preset} in {root}")
        write_report(root, directories, task_name, option, complexities, modes, clips)
        return 0

    import jax
    if config.distributed:
        jax.distributed.initialize()
    from tqdm import tqdm
    from stablebptt import runs
    root = Path(config.out) / config.preset
    root.mkdir(parents=True, exist_ok=True)
    seeds = [42 + s for s in range(config.seeds)]
    try:
        per_cell = takes_per_cell(make_task(task_name, option, complexities[0], config), option)
    except InputError as error:
        fail(str(error))
    programs = plan_programs(complexities, modes, clips, seeds, per_cell, option, root)
    try:
        for program in programs:
            check_resumable(program, task_name, option, config)
    except InputError as error:
        fail(str(error))
    placement = place(programs, jax.devices(), jax.process_index())
    wall = time.perf_counter()
    deadline = time.monotonic() + config.time_limit if config.time_limit else None
    failed = threading.Event()
    should_stop = lambda: failed.is_set() or (deadline is not None and time.monotonic() > deadline)
    log = lambda message: tqdm.write(message, file=sys.stderr)

    def run_queue(devices, queue, interrupted):
        """The programs placed on one device group, one after another; groups run side by side."""
        outcomes = []
        for program in queue:
            if failed.is_set() or interrupted():
                break
            try:
                outcome = run_program(program, task_name, option, config, devices, log,
                                      lambda: should_stop() or interrupted())
            except BaseException:
                failed.set()  # the other groups checkpoint and stop instead of running to their end
                raise
            rows = outcome.pop("rows")
            if len(rows):
                write_cells(program, rows, task_name, option, config, root)
            outcomes.append(outcome)
        return outcomes

    # A signal (Ctrl-C, SIGTERM, SIGHUP) sets a flag, as in train.py: every program checkpoints
    # after its current epoch and stops.
    with stop_on_signals(log) as interrupted:
        # Threads only dispatch: compiling and running release the GIL, so the groups' programs overlap.
        with ThreadPoolExecutor(max_workers=max(1, len(placement))) as pool:  # a host may get no program
            futures = [pool.submit(run_queue, devices, queue, interrupted) for devices, queue in placement]
            # A timed wait, not a blocking one: the OS may deliver a signal to any thread, and Python
            # runs the handler only once the main thread runs again.
            while futures_wait(futures, timeout=0.5).not_done:
                pass
            report = [outcome for future in futures for outcome in future.result()]
    if interrupted():
        print("interrupted: the programs checkpointed; run the same command again to resume", file=sys.stderr)
        return 130
    finished = all(r["epochs_done"] == config.epochs for r in report)
    # One record per call, never overwritten: calls may run side by side (one per GPU) or resume.
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    ran = [value for _, queue in placement for program in queue for value in program.values]
    host = f"-host{jax.process_index()}" if jax.process_count() > 1 else ""
    record = root / "sweeps" / f"{stamp}{host}-{option}{'_'.join(map(str, ran))}.json"
    record.parent.mkdir(exist_ok=True)
    runs.write_json(record, {
        "preset": config.preset, "config": dataclasses.asdict(config), "finished": finished,
        "devices": [str(d) for d in jax.devices()], "device_kind": jax.devices()[0].device_kind,
        "wall_seconds_this_call": time.perf_counter() - wall, "programs": report})
    # The report covers every run directory of the preset, also those of earlier or parallel calls.
    write_report(root, run_directories(root, task_name, option), task_name, option, PRESETS[config.preset][2], modes, clips)
    print(f"{'done' if finished else 'stopped at the time limit; run again to resume'}: {root} (record: {record.name})")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
