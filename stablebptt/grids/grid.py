"""Grids of runs: task option x mode x clip mode x seeds, trained as few compiled programs.

Everything that does not change the compiled program is vmapped into one
program: seeds, mode (each cell computes R, M and S and its mode selects), clip
mode and threshold, learning rate, and a task option that enters only the loss
(``Task.cell_option``: repulsion's rc, quantum's target). An option that changes
the model (cart-pole's poles) makes one program per value. Programs spread over
the devices (``place``): each takes a group of devices and runs beside the
others, its cells sharded over its group; under jax.distributed each host runs
the programs placed on its own devices. Every cell ends as a run folder of the
single-run schema (``stablebptt.runs.run_folder``), and ``stablebptt.grids.report`` rebuilds the grid's
tables and figures from those folders.
"""
from __future__ import annotations

import dataclasses
import itertools
import json
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import wait as futures_wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from stablebptt import storage
from stablebptt.engine import fitting, starting
from stablebptt.engine.config import CLIP_MODES, TrainConfig
from stablebptt.engine.metrics import empty_rows
from stablebptt.engine.program_store import code_digest
from stablebptt.engine.task import Task
from stablebptt.engine.training import make_trainer
from stablebptt.errors import InputError
from stablebptt.flows.modes import MODES
from stablebptt.grids.pieces import identity_as_recorded
from stablebptt.grids.report import cell_name
from stablebptt.runs import model_store, run_folder
from stablebptt.timing import compile_ahead


@dataclass(frozen=True)
class Grid:
    """A grid of cells (value, mode, clip, seed) and how to train it.

    Attributes:
      task_name, option: the task and the option whose ``values`` the grid varies.
      make_task, task_config: a value -> its task, and the task configuration recorded per cell.
      modes, clips, seeds: the other axes.
      epochs, train_size, test_size, checkpoint_every: as in ``TrainConfig``
        (``checkpoint_every`` also paces the progress log).
      checkpoint_seconds: the least wall time between two checkpoints (the end
        and a stop always save).
      unroll: rollout steps per loop iteration (0: ``gpu_unroll`` on GPUs, 1 on CPUs).
      group_values: vmap the values into one program where the task takes them per cell.
      name: recorded in each cell's config.json (the sweep's preset, or the task's name).
      identity: more of what a program's checkpoint belongs to (e.g. a horizon override).
      train_option: the grid varies this ``TrainConfig`` field (one of ``PER_CELL_TRAINING``, e.g.
        ``"lr"``) instead of a task option; ``make_task`` and ``task_config`` then ignore the value,
        and every value trains in one program, as a per-cell hyperparameter of the optimizer.
    """

    task_name: str
    option: str
    values: tuple
    make_task: Callable[[Any], Task]
    task_config: Callable[[Any], Any]
    modes: tuple = MODES
    clips: tuple = CLIP_MODES
    seeds: tuple = (42,)
    epochs: int = 1000
    train_size: int = 256
    test_size: int = 256
    checkpoint_every: int = 10
    checkpoint_seconds: float = 30.0
    unroll: int = 0
    gpu_unroll: int = 1
    group_values: bool = True
    name: str = ""
    identity: dict = field(default_factory=dict)
    train_option: str = ""

    def train_overrides(self, value) -> dict:
        """What ``value`` sets in a cell's TrainConfig."""
        return {self.train_option: value} if self.train_option else {}


# TrainConfig fields a grid can vary per cell inside one program -> the optimizer hyperparameter
# that holds them (``make_optimizer`` injects both).
PER_CELL_TRAINING = {"lr": "learning_rate", "clip_threshold": "clip_threshold"}


@dataclass
class Program:
    """One compiled program: one or more values of the grid, all their cells vmapped."""

    values: list  # the values this program trains
    cells: list  # (value, mode, clip, seed) per cell
    directory: Path
    per_cell: bool  # the values enter as per-cell inputs of one program (Task.cell_option or the optimizer)


def write_record(root: Path, record: dict, report: list[dict]) -> Path:
    """This call's record, ``root/sweeps/<time>[-host<i>]-<option><values>.json`` (never overwritten:
    calls may run side by side, one per GPU, or resume): ``record`` with the devices and the programs'
    ``report``. Under jax.distributed, waits until every host has written its cells."""
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    ran = "_".join(str(value) for program in report for value in program["complexity"])
    host = f"-host{jax.process_index()}" if jax.process_count() > 1 else ""
    path = root / "sweeps" / f"{stamp}{host}-{record.get('option', '')}{ran}.json"
    path.parent.mkdir(exist_ok=True)
    storage.write_json(path, {**record, "devices": [str(d) for d in jax.devices()],
                           "device_kind": jax.devices()[0].device_kind, "programs": report})
    if jax.process_count() > 1:  # every host's cells are written before process 0 reports on them
        from jax.experimental import multihost_utils
        multihost_utils.sync_global_devices("stablebptt grid: cells written")
    return path


def takes_per_cell(task: Task, option: str) -> bool:
    return task.cell_option is not None and task.cell_option.name == option


def plan(grid: Grid, root: Path) -> list[Program]:
    """One program for all values where the task takes them per cell (and ``group_values``), else one per value."""
    per_cell = bool(grid.train_option) or (grid.group_values and takes_per_cell(grid.make_task(grid.values[0]), grid.option))
    groups = [list(grid.values)] if per_cell else [[value] for value in grid.values]
    return [Program(group, [(v, m, c, s) for v, m, c, s in itertools.product(group, grid.modes, grid.clips, grid.seeds)],
                    root / "_programs" / f"{grid.option}{'_'.join(map(str, group))}", per_cell) for group in groups]


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


def _identity(program: Program, grid: Grid) -> dict:
    """What a program's checkpoint belongs to; a resume must match it."""
    return {"cells": [list(c) for c in program.cells], "task": grid.task_name, grid.option: program.values,
            "train_size": grid.train_size, "test_size": grid.test_size, **grid.identity}


def check_resumable(program: Program, grid: Grid) -> None:
    identity_file = program.directory / "cells.json"
    if not identity_file.exists():
        return
    found = storage.read_json(identity_file)
    mine = identity_as_recorded(_identity(program, grid), found)
    if found != mine:
        changed = (" (the model file's contents changed since it trained: restore the file, or train the changed "
                   "model into another output folder, --out)" if found.get("inputs") != mine.get("inputs") else "")
        raise InputError(f"{program.directory} holds a checkpoint of a different grid{changed}: choose another output "
                         "folder (--out) or remove it")


@dataclass
class Prepared:
    """A program ready to train: its compiled epoch, inputs and where training stands."""

    program: Program
    devices: list
    epoch_fn: Callable
    arguments: tuple
    state: Any
    start: int
    rows: np.ndarray
    train_config: TrainConfig
    unroll: int
    padded_cells: int
    compile_seconds: float
    steps_per_epoch: int  # env steps a cell trains in an epoch


def prepare(program: Program, grid: Grid, devices: list) -> Prepared:
    """Build one program's trainer on its devices, resume its checkpoint and compile its epoch.

    Runs in any thread: the programs of a device group compile side by side on the
    host's cores while the first of them trains.
    """
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    task = grid.make_task(program.values[0])
    # The task's GPU choice unrolls at most one window (a short --steps); a grid's own unroll is checked as given.
    unroll = grid.unroll or (min(grid.gpu_unroll, task.dynamics.horizon) if devices[0].platform == "gpu" else 1)
    count = len(program.cells)
    cells = program.cells + [program.cells[-1]] * (-count % len(devices))  # pad to a multiple of the devices
    train_config = TrainConfig(epochs=grid.epochs, seeds=len(cells), train_size=grid.train_size,
                               test_size=grid.test_size, seed_batching="vmap", checkpoint_every=grid.checkpoint_every,
                               unroll=unroll)
    trainer = make_trainer(task, train_config, grid=True)
    sharding = NamedSharding(Mesh(np.array(devices), ("cells",)), PartitionSpec("cells"))
    shard = lambda tree: jax.device_put(tree, sharding)

    seeds = jnp.array([seed for _, _, _, seed in cells], dtype=jnp.uint32)
    state = trainer.init(seeds)
    hyper = dict(state.opt_state.hyperparams)
    hyper["mode_index"] = jnp.array([MODES.index(mode) for _, mode, _, _ in cells], dtype=hyper["mode_index"].dtype)
    hyper["clip_index"] = jnp.array([CLIP_MODES.index(clip) for _, _, clip, _ in cells], dtype=hyper["clip_index"].dtype)
    if grid.train_option:
        name = PER_CELL_TRAINING[grid.train_option]
        hyper[name] = jnp.array([value for value, _, _, _ in cells], dtype=hyper[name].dtype)
    state = state._replace(opt_state=state.opt_state._replace(hyperparams=hyper))
    program.directory.mkdir(parents=True, exist_ok=True)
    storage.write_json(program.directory / "cells.json", _identity(program, grid))
    # Checkpoints hold the real cells only, so a program resumes on any number of devices.
    if (program.directory / run_folder.CHECKPOINT_FILE).exists():
        start, loaded, rows = run_folder.load_checkpoint(program.directory, _unpad(state, count))
        state = jax.tree.map(lambda fresh, saved: fresh.at[:count].set(saved), state, loaded)
    else:
        start, rows = 0, empty_rows()
    state = shard(state)
    takes_values = program.per_cell and not grid.train_option  # the task's cell option
    values = shard(jnp.asarray([value for value, _, _, _ in cells])) if takes_values else None
    arguments = (values, trainer.batches, trainer.train_states, trainer.test_states)
    epoch_fn, compile_seconds = compile_ahead(trainer.epoch, state, *arguments)
    refill, refill_seconds = starting.compiled_refill(trainer, state)  # training on episodes: each epoch's start
    return Prepared(program, devices, lambda state, *rest: epoch_fn(refill(state), *rest), arguments, state, start,
                    rows, train_config, unroll, len(cells), compile_seconds + refill_seconds,
                    fitting.env_steps_per_epoch(trainer, train_config))


def _unpad(tree, count: int):
    return jax.tree.map(lambda a: a[:count], tree)


def train_prepared(prepared: Prepared, grid: Grid, log: Callable[[str], None],
                   should_stop: Callable[[], bool]) -> dict:
    """Train every cell of one prepared program to ``grid.epochs``.

    ``should_stop()`` true (time limit, a signal, another program failed) checkpoints and returns early.
    Returns the program's record, with its metric rows, final parameters and train config.
    """
    program, count = prepared.program, len(prepared.program.cells)
    epoch_fn, arguments, start = prepared.epoch_fn, prepared.arguments, prepared.start
    cell_index = np.arange(count)
    started = time.perf_counter()

    def run_epoch(state):
        state, metrics = epoch_fn(state, *arguments)
        # A diverged cell keeps its NaNs in the table; vmapped cells cannot affect each other.
        return state, _unpad(jax.device_get(metrics), count)

    def save(epoch, state, rows):
        run_folder.save_checkpoint(program.directory, epoch, _unpad(state, count), rows)

    def report(epoch, metrics):
        if epoch % grid.checkpoint_every == 0 or epoch == grid.epochs:
            log(f"{grid.task_name} {grid.option}={','.join(map(str, program.values))}: epoch {epoch}/{grid.epochs}, "
                f"{(time.perf_counter() - started) / max(epoch - start, 1):.2f} s/epoch for {count} cells "
                f"on {len(prepared.devices)} device(s)")

    _, epoch, state, rows, _ = fitting.fit(run_epoch, prepared.state, start, grid.epochs, prepared.rows, cell_index, save,
                                        grid.checkpoint_every, should_stop, report,
                                        checkpoint_seconds=grid.checkpoint_seconds,
                                        steps_per_epoch=prepared.steps_per_epoch)
    return {"complexity": program.values, "epochs_done": int(epoch), "cells": count, "unroll": prepared.unroll,
            "train_config": prepared.train_config, "params": jax.device_get(_unpad(state, count).params),
            "devices": [str(d) for d in prepared.devices], "padded_cells": prepared.padded_cells,
            "compile_seconds": prepared.compile_seconds, "train_seconds": time.perf_counter() - started, "rows": rows}


def cell_groups(program: Program) -> dict[tuple, list[tuple[int, int]]]:
    """(value, mode, clip) -> its (index in the program, seed) pairs: one run folder each."""
    groups: dict[tuple, list[tuple[int, int]]] = {}
    for index, (value, mode, clip, seed) in enumerate(program.cells):
        groups.setdefault((value, mode, clip), []).append((index, seed))
    return groups


def write_cells(program: Program, outcome: dict, grid: Grid, root: Path, shared: model_store.SharedModels) -> None:
    """Split a program's rows and parameters into one run folder per (value, mode, clip), seeds as
    rows: config.json, metrics.csv and params.npz of the single-run schema, so every cell renders,
    plots and reopens (``stablebptt.apps.trained``) as a single run does."""
    rows, params = outcome["rows"], outcome["params"]
    for (value, mode, clip), members in cell_groups(program).items():
        directory = root / cell_name(grid.task_name, grid.option, value, mode, clip)
        selected = []
        for index, seed in members:
            part = rows[rows[:, 1] == index].copy()
            part[:, 1] = seed
            selected.append(part)
        table = np.concatenate(selected)
        table = table[np.lexsort((table[:, 1], table[:, 0]))]
        seeds = [seed for _, seed in members]
        assert seeds == list(range(seeds[0], seeds[0] + len(seeds)))  # as TrainConfig's seed and seeds name them
        train = dataclasses.replace(outcome["train_config"], mode=mode, clip=clip, seeds=len(members), seed=seeds[0],
                                    epochs=grid.epochs, **grid.train_overrides(value))
        task = grid.make_task(value)
        record = run_folder.run_record(grid.task_name, grid.task_config(value), train, task, sweep=grid.name)
        indices = np.array([index for index, _ in members])
        write_cell(directory, record, table, jax.tree.map(lambda leaf: np.asarray(leaf)[indices], params),
                   task.resolved.get("model_file"), shared)


def write_cell(directory: Path, record: dict, rows: np.ndarray, params, model_file: str | Path | None = None,
               shared: model_store.SharedModels | None = None) -> None:
    """One cell's run folder: config.json, metrics.csv and params.npz (seeds stacked on the leaves' first
    axis); and what reopens ``model_file`` after it moved, its compiled copy shared by the grid's cells
    (one file per model in ``<grid root>/models``, compiled once per grid by ``shared``)."""
    directory.mkdir(parents=True, exist_ok=True)
    run_folder.write_config(directory, record)
    run_folder.write_metrics(directory / run_folder.METRICS_FILE, rows)
    run_folder.save_params(directory / run_folder.PARAMS_FILE, params)
    if model_file:
        shared = shared or model_store.SharedModels(directory.parent)
        model_store.link_model(directory, model_file, shared(model_file))


def describe(grid: Grid, first_seed: int, seeds: int) -> dict:
    """What makes the cells of several calls one grid, as JSON: every axis, setting and task option
    (``seeds`` seeds from ``first_seed``), and the code's digest."""
    description = {"name": grid.name, "task": grid.task_name, "option": grid.option, "values": list(grid.values),
                   "train_option": grid.train_option, "modes": list(grid.modes), "clips": list(grid.clips),
                   "first_seed": first_seed, "seeds": seeds, "epochs": grid.epochs, "train_size": grid.train_size,
                   "test_size": grid.test_size, "identity": grid.identity,
                   "task_configs": [dataclasses.asdict(grid.task_config(value)) for value in grid.values],
                   "code": code_digest()}
    return json.loads(json.dumps(description))


# What a cell's config.json says of the grid that filled it; a grid may rewrite only its own cells.
CELL_IDENTITY = ("mode", "clip", "epochs", "seed", "seeds", "train_size", "test_size", "lr", "clip_threshold")


def _cell_identities(program: Program, grid: Grid, root: Path) -> dict[Path, dict]:
    """Each cell folder this program writes -> what its config.json will say of the grid."""
    return {root / cell_name(grid.task_name, grid.option, value, mode, clip): {
        "task": grid.task_name, "task_config": dataclasses.asdict(grid.task_config(value)), "sweep": grid.name,
        "train": {"mode": mode, "clip": clip, "epochs": grid.epochs, "seed": members[0][1], "seeds": len(members),
                  "train_size": grid.train_size, "test_size": grid.test_size, "lr": TrainConfig.lr,
                  "clip_threshold": TrainConfig.clip_threshold, **grid.train_overrides(value)}}
        for (value, mode, clip), members in cell_groups(program).items()}


def check_cells_are_this_grids(programs: list[Program], grid: Grid, root: Path) -> None:
    """Refuse, before anything trains, to write over cells that another grid filled (other epochs,
    seeds or task options): their results would be lost."""
    foreign = []
    for program in programs:
        if (program.directory / "cells.json").exists():
            continue  # this grid's own checkpoint (check_resumable matched it): it resumes, or trains further
        for directory, mine in _cell_identities(program, grid, root).items():
            if not (directory / run_folder.CONFIG_FILE).exists():
                continue
            theirs = storage.read_json(directory / run_folder.CONFIG_FILE)
            found = {"task": theirs.get("task"), "task_config": theirs.get("task_config"), "sweep": theirs.get("sweep"),
                     "train": {name: theirs.get("train", {}).get(name) for name in CELL_IDENTITY}}
            if found != mine:
                differs = [name for name in CELL_IDENTITY if found["train"][name] != mine["train"][name]]
                differs += [name for name in ("task", "task_config", "sweep") if found[name] != mine[name]]
                foreign.append(f"{directory.name} ({', '.join(differs)})")
    if foreign:
        raise InputError(f"{root} holds {len(foreign)} cell(s) another grid filled, which this one would overwrite: "
                         f"{'; '.join(foreign[:3])}{' ...' if len(foreign) > 3 else ''}: choose another output folder "
                         "(--out)")


def run_grid(grid: Grid, root: Path, should_stop: Callable[[], bool] = lambda: False,
             log: Callable[[str], None] = print) -> list[dict]:
    """Train this process's share of the grid into ``root``, resuming from checkpoints; runs in any thread.

    Programs go to device groups (``place``); the groups run side by side in threads (which only
    dispatch: compiling and running release the GIL), each group's programs compiled together and
    trained one after another.
    A failing program stops the others at their next epoch. Returns each program's record.

    Raises:
      InputError: a checkpoint in ``root`` belongs to a different grid.
    """
    programs = plan(grid, root)
    for program in programs:
        check_resumable(program, grid)
    check_cells_are_this_grids(programs, grid, root)
    placement = place(programs, jax.devices(), jax.process_index())
    shared = model_store.SharedModels(root)  # each model compiled and kept once for all the grid's cells
    failed = threading.Event()
    stop = lambda: failed.is_set() or should_stop()

    def run_queue(devices, queue):
        outcomes = []
        # Every program of the queue compiles at once, in threads (compiling releases the GIL and
        # uses the host's cores), so later programs are ready when the device is free for them.
        compiler = ThreadPoolExecutor(max_workers=len(queue))
        ready = [compiler.submit(prepare, program, grid, devices) for program in queue]
        compiler.shutdown(wait=False, cancel_futures=True)  # a stop cancels the compiles not yet begun
        for program, prepared in zip(queue, ready):
            if stop():
                break
            try:
                outcome = train_prepared(prepared.result(), grid, log, stop)
            except BaseException:
                failed.set()  # the other groups checkpoint and stop instead of running to their end
                raise
            if len(outcome["rows"]):
                write_cells(program, outcome, grid, root, shared)
            for name in ("rows", "params", "train_config"):  # what the record does not keep
                outcome.pop(name)
            outcomes.append(outcome)
        return outcomes

    with ThreadPoolExecutor(max_workers=max(1, len(placement))) as pool:  # a host may get no program
        futures = [pool.submit(run_queue, devices, queue) for devices, queue in placement]
        # A timed wait, not a blocking one: a signal handler of the calling (main) thread runs
        # only once that thread runs Python again.
        while futures_wait(futures, timeout=0.5).not_done:
            pass
        return [outcome for future in futures for outcome in future.result()]
