#!/usr/bin/env python3
"""Run a grid (task x complexity x mode x clip mode x seeds), one compiled program per complexity.

    python scripts/sweep.py --preset cartpole                 # 1-4 poles x R/M/C/S x value/norm/none x 5 seeds
    python scripts/sweep.py --preset repulsion --epochs 200
    python scripts/sweep.py --preset quantum --time-limit 540 # stop and checkpoint before 9 minutes; rerun resumes

Everything that does not change the compiled program is vmapped into one
program per complexity: seeds, mode (each cell computes R, M and S and its mode
selects), clip mode and threshold, learning rate. The cell axis is sharded
over every visible device (jax.sharding); with --distributed, jax.distributed
spans several hosts. Sharding halves the time only where a GPU is busy: on an
H200 a 60-cell program is bound by kernel latency (240 cells cost 1.2x of 60),
so two GPUs serve best as one process each (CUDA_VISIBLE_DEVICES) on different
complexities, or with more seeds. Results land in
OUT/PRESET/: one run directory per (complexity, mode, clip) with the seeds as
rows (scripts/plot.py reads them), summary.csv with the final test loss per
cell, learning-curve figures, and sweeps/<time>-<complexities>.json per call with
wall times and devices.
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import dataclasses  # noqa: E402
import itertools  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402

from stablebptt.cli import build, fail, parse_config  # noqa: E402
from stablebptt.errors import InputError  # noqa: E402

# preset -> (task, the option that sets the complexity, its values)
PRESETS = {
    "cartpole": ("cartpole", "poles", (1, 2, 3, 4)),
    "repulsion": ("repulsion", "rc", (1.0, 0.1, 0.01, 0.001)),
    "quantum": ("quantum", "target", (3, 4, 5)),
    "tiny": ("repulsion", "rc", (0.1,)),  # the CPU test of the machinery
}
# Rollout-loop unrolling on GPUs, measured on an H200 (60 cells; s/epoch):
# cart-pole 1.10 -> 0.69-0.84 at 5, quantum 0.68 -> 0.42 at 8, repulsion 0.20 -> 0.12 at 10.
# Beyond that compile time grows faster than the gain (cart-pole: 80 s at 10).
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
    """One compiled program: one complexity of the grid, all its cells vmapped."""

    complexity: object
    cells: list  # (mode, clip, seed) per cell
    directory: Path


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


def run_program(program: Program, task_name: str, option: str, config: SweepConfig, log, deadline: float | None) -> dict:
    """Train every cell of one program to config.epochs, resuming from its checkpoint."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec
    import tasks
    from stablebptt import runs
    from stablebptt.training import CLIP_MODES, MODES, TrainConfig, make_trainer

    module = tasks.load(task_name)
    task_options = {option: program.complexity}
    if config.task_steps:
        task_options["steps"] = config.task_steps
    task = module.make(build(module.Config, task_options))
    devices = jax.devices()
    unroll = config.unroll or (GPU_UNROLL.get(task_name, 1) if devices[0].platform == "gpu" else 1)
    task = dataclasses.replace(task, dynamics=dataclasses.replace(task.dynamics, unroll=unroll))
    cells = list(program.cells)
    cells += [cells[-1]] * (-len(cells) % len(devices))  # pad to a multiple of the devices; dropped later
    train_config = TrainConfig(epochs=config.epochs, seeds=len(cells), train_size=config.train_size,
                               test_size=config.test_size, seed_batching="vmap", checkpoint_every=config.checkpoint_every)
    trainer = make_trainer(task, train_config, grid=True)
    sharding = NamedSharding(Mesh(np.array(devices), ("cells",)), PartitionSpec("cells"))
    shard = lambda tree: jax.device_put(tree, sharding)

    seeds = jnp.array([seed for _, _, seed in cells], dtype=jnp.uint32)
    state = trainer.init(seeds)
    hyper = dict(state.opt_state.hyperparams)
    hyper["mode_index"] = jnp.array([MODES.index(mode) for mode, _, _ in cells], dtype=hyper["mode_index"].dtype)
    hyper["clip_index"] = jnp.array([CLIP_MODES.index(clip) for _, clip, _ in cells], dtype=hyper["clip_index"].dtype)
    state = state._replace(opt_state=state.opt_state._replace(hyperparams=hyper))
    program.directory.mkdir(parents=True, exist_ok=True)
    identity = {"cells": [list(c) for c in cells], "task": task_name, option: program.complexity,
                "train_size": config.train_size, "test_size": config.test_size, "task_steps": config.task_steps}
    identity_file = program.directory / "cells.json"
    if identity_file.exists() and runs.read_json(identity_file) != identity:
        raise InputError(f"{program.directory} holds a checkpoint of a different grid: choose another --out or remove it")
    runs.write_json(identity_file, identity)
    if (program.directory / runs.CHECKPOINT_FILE).exists():
        start, state, rows = runs.load_checkpoint(program.directory, state)
    else:
        start, rows = 0, runs.empty_rows()
    state = shard(state)
    arguments = (trainer.batches, trainer.train_states, trainer.test_states)
    started = time.perf_counter()
    epoch_fn = trainer.epoch.lower(state, *arguments).compile()
    compile_seconds = time.perf_counter() - started
    cell_index = np.arange(len(cells))
    epoch = start
    for epoch in range(start + 1, config.epochs + 1):
        if deadline and time.monotonic() > deadline:
            epoch -= 1
            break
        tick = time.perf_counter()
        state, metrics = epoch_fn(state, *arguments)
        metrics = jax.device_get(metrics)
        # A diverged cell keeps its NaNs in the table; vmapped cells cannot affect each other.
        rows = np.concatenate([rows, runs.epoch_rows(epoch, cell_index, metrics, time.perf_counter() - tick)])
        if epoch % config.checkpoint_every == 0 or epoch == config.epochs or (deadline and time.monotonic() > deadline):
            runs.save_checkpoint(program.directory, epoch, state, rows)
            log(f"{task_name} {option}={program.complexity}: epoch {epoch}/{config.epochs}, "
                f"{(time.perf_counter() - started - compile_seconds) / max(epoch - start, 1):.2f} s/epoch for {len(cells)} cells")
            if deadline and time.monotonic() > deadline:
                break
    return {"complexity": program.complexity, "epochs_done": int(epoch), "cells": len(program.cells), "unroll": unroll,
            "padded_cells": len(cells), "compile_seconds": compile_seconds,
            "train_seconds": time.perf_counter() - started - compile_seconds, "rows": rows}


def write_cells(program: Program, rows, task_name: str, option: str, config: SweepConfig, root: Path) -> None:
    """Split a program's rows into one run directory per (mode, clip), seeds as rows."""
    import numpy as np
    from stablebptt import runs
    groups = {}
    for index, (mode, clip, seed) in enumerate(program.cells):
        groups.setdefault((mode, clip), []).append((index, seed))
    for (mode, clip), members in groups.items():
        directory = root / cell_name(task_name, option, program.complexity, mode, clip)
        directory.mkdir(parents=True, exist_ok=True)
        selected = []
        for index, seed in members:
            part = rows[rows[:, 1] == index].copy()
            part[:, 1] = seed
            selected.append(part)
        table = np.concatenate(selected)
        table = table[np.lexsort((table[:, 1], table[:, 0]))]
        runs.write_json(directory / runs.CONFIG_FILE, {
            "task": task_name, "task_config": {option: program.complexity},
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


def write_report(root: Path, directories: list[Path], task_name, option, complexities, modes, clips) -> None:
    """summary.csv, table.md and one learning-curve figure per complexity, from the run directories."""
    from stablebptt.plots import learning_curves
    from stablebptt.runs import atomic_write
    summarize(root, directories)
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
    programs = [Program(value, [(m, c, s) for m, c, s in itertools.product(modes, clips, seeds)],
                        root / "_programs" / f"{option}{value}") for value in complexities]
    wall = time.perf_counter()
    deadline = time.monotonic() + config.time_limit if config.time_limit else None
    report = []
    for program in programs:
        try:
            outcome = run_program(program, task_name, option, config, lambda message: tqdm.write(message, file=sys.stderr), deadline)
        except InputError as error:
            fail(str(error))
        rows = outcome.pop("rows")
        rows = rows[rows[:, 1] < len(program.cells)]  # drop the device padding
        if len(rows):
            write_cells(program, rows, task_name, option, config, root)
        report.append(outcome)
    finished = all(r["epochs_done"] == config.epochs for r in report)
    # One record per call, never overwritten: calls may run side by side (one per GPU) or resume.
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    record = root / "sweeps" / f"{stamp}-{option}{'_'.join(str(p.complexity) for p in programs)}.json"
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
