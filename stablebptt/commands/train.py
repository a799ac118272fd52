#!/usr/bin/env python3
"""Train a controller by backpropagation through time with gradient flow R, M, S or C.

    python scripts/train.py --poles 3                  # cart-pole with 3 poles (MJX)
    python scripts/train.py --model my_robot.xml       # any MJCF
    python scripts/train.py --task repulsion --rc 0.01 --mode C --seeds 5
    python scripts/train.py --resume runs/cartpole_3-20261122-101500
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from stablebptt import tasks
from stablebptt.cli import (Parser, add_options, build, fail, leave_out_unused_backends, one_line_errors, option_name,
                            path_named, typed_option)
from stablebptt.commands import task_options
from stablebptt.engine import metrics
from stablebptt.engine.config import TrainConfig, batches_divide
from stablebptt.runs import epochs

RUNS_ROOT = Path("runs")
# What --resume may change: extending a run, in epochs or in time, and the devices it spans (which change
# its numbers only in their rounding).
RESUMABLE = {"epochs", "budget", "devices"}
UNTIL_BUDGET = 1_000_000  # the epochs of a run given --budget and no --epochs


def parse(argv: list[str]):
    parser = Parser(description=__doc__, formatter_class=lambda prog: argparse.RawDescriptionHelpFormatter(prog, max_help_position=32))
    parser.add_argument("--out", type=path_named, default=None, help="run directory to create (default: runs/TASK-TIME); never overwritten")
    parser.add_argument("--resume", type=path_named, default=None, help="continue the run in this directory from its checkpoint")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar (logs and CI)")
    parser.add_argument("--compile-cache", action=argparse.BooleanOptionalAction, default=True,
                        help="keep compiled programs between runs (in $STABLEBPTT_COMPILE_CACHE or ~/.cache/stablebptt; default: on)")
    # owners: option -> the configs that have it ("train" or task names)
    owners = {name: {"train"} for name in add_options(parser, TrainConfig, "training",
                                                      defaults=task_options.train_defaults_by_task(TrainConfig))}
    owners = task_options.add_task_options(parser, owners)  # before parsing: the task options are options too
    env_module = tasks.load("env")
    parser.add_argument("--recipe", choices=sorted(env_module.RECIPES), default=None,
                        help="options measured together, for an --env: " + "; ".join(
                            recipe_help(name, env_module) for name in sorted(env_module.RECIPES))
                        + " (an option given beside it wins, and leaves out what the recipe set for the value it "
                          "replaces: --no-critic the critic's settings and HopperStand's cut, --no-learn-action-noise "
                          "the entropy, --action-noise 0 both, --episodes off the critic, the noise, --batch 256 and the "
                          "cut, --episode-length the cut)")
    return parser.parse_args(argv), owners


def configure(args, owners):
    """(task name, task config, train config, run dir, the run's record or None) from the command line or a run."""
    given = {name: value for name, value in vars(args).items() if name in owners}
    if args.resume is not None:
        changed = [option_name(name) for name in sorted(set(given) - RESUMABLE)]
        changed += [flag for flag, value in (("--out", args.out), ("--task", args.task), ("--recipe", args.recipe))
                    if value is not None]
        if changed:
            fail(f"--resume continues a run with its saved configuration; only --epochs, --budget and --devices may be given (got {changed[0]})")
        from stablebptt.apps.trained import configs_of
        from stablebptt.runs import run_folder
        record = run_folder.open_run(args.resume)
        task_name = tasks.canonical(record["task"])
        task_config, train_config = configs_of(args.resume, record, given)
        if check_resume := getattr(tasks.load(task_name), "check_resume", None):
            if note := check_resume(task_config, record):  # what cannot be checked is said, once
                print(note, file=sys.stderr)
        return task_name, task_config, train_config, args.resume, record
    task_name = task_options.choose_task(args, owners, "train")
    recipe = {}
    if args.recipe is not None:
        recipe = tasks.load("env").recipe_options(args.recipe, given.get("env", ""), given)
        if task_name != "env":
            fail(f"--recipe {args.recipe} is for an environment (--env NAME), not --task {task_name}")
    defaults = tasks.train_defaults(task_name)
    if given.get("budget", 0) > 0 and "epochs" not in given:  # a budget alone bounds the run: it trains until spent
        defaults["epochs"] = UNTIL_BUDGET
    chosen = {**recipe, **given}
    # From fixed starts the batch splits the training states: a task's default batch of carried episodes (an env's 64
    # of its 16 starts) that does not is one batch of them all.
    train_size = chosen.get("train_size", defaults.get("train_size", TrainConfig.train_size))
    default_batch = defaults.get("batch", TrainConfig.batch)
    if chosen.get("episodes") == "off" and "batch" not in chosen and not batches_divide(train_size, default_batch):
        defaults["batch"] = train_size
    from stablebptt.engine.checks import check_options
    from stablebptt.errors import InputError
    try:
        train_config = build(TrainConfig, {**defaults, **chosen})
        task_config = task_options.task_config(task_name, chosen)
        check_options(train_config, task_config)  # a resumed run keeps what it recorded
    except InputError as error:
        if not recipe:
            raise
        raise InputError(f"{error} (--recipe {args.recipe} sets {recipe_words(recipe)})") from None
    return task_name, task_config, train_config, args.out, None


def recipe_help(name: str, env_module) -> str:
    """A recipe as ``--help`` names it: its options, then those it sets on particular envs."""
    on_envs = env_module.RECIPES_BY_ENV.get(name, {}).items()
    return f"{name}: {recipe_words(env_module.RECIPES[name])}" + "".join(
        f", on {env}: {recipe_words(options)}" for env, options in on_envs)


def recipe_words(recipe: dict) -> str:
    """A recipe's options as typed: ``--steps 32 --critic``."""
    return " ".join(typed_option(name, value) for name, value in recipe.items())


def main(argv: list[str]) -> int:
    leave_out_unused_backends()  # before parsing, which imports the tasks and MJX with them
    held: list = []  # the run folder in use, its lock released however main ends (in a process, the OS would)
    try:
        return train(argv, held)
    finally:
        for run in held:
            run.close()


def train(argv: list[str], held: list) -> int:
    started = time.perf_counter()
    args, owners = parse(argv)
    with one_line_errors():
        task_name, task_config, train_config, run_dir, record = configure(args, owners)

    import jax  # after parsing: --x64 must be set before any array exists
    jax.config.update("jax_enable_x64", train_config.x64)
    jax.config.update("jax_default_matmul_precision", train_config.matmul_precision)
    from stablebptt.runtime import use_compile_cache
    use_compile_cache(args.compile_cache)
    from stablebptt.errors import StorageError
    from stablebptt.runs import session

    with one_line_errors():
        begun = session.begin(tasks.load(task_name), task_name, task_config, train_config, run_dir, record, RUNS_ROOT)
    held.append(begun.run)
    run, task, seeds, start_epoch, rows = begun.run, begun.task, begun.seeds, begun.start_epoch, begun.rows
    run_dir = run.directory
    task_label, resuming = run.name, run.resuming
    if run.repaired:
        print(f"rewrote {' and '.join(run.repaired)} of {run_dir} from its checkpoint (epoch {start_epoch})", file=sys.stderr)

    if task.summary:
        print(task.summary)
    if begun.trainer.episodes is not None:
        extras = (f", its return bootstrapped by a learned value of its last state (TD({train_config.td_lambda:g}) "
                  "targets" + (f"; the least of {train_config.critics} networks'" if train_config.critics > 1 else "")
                  + ")") if train_config.critic else ""
        if train_config.value_at_time_limit:
            extras += ", and of the state where its episode's length cuts it"
        if train_config.training_episode_length:
            extras += f", each episode cut at {train_config.training_episode_length} steps and started again"
        if train_config.value_at_gradient_cut:
            extras += ", the states where its step cuts the derivative valued for the actions before them"
        if train_config.learn_action_noise:
            extras += (f", Gaussian noise on its actions of standard deviations learned from "
                       f"{train_config.action_noise:g}")
            if train_config.entropy:
                extras += f", the noise's entropy weighed {train_config.entropy:g} in its loss"
        elif train_config.action_noise:
            extras += f", Gaussian noise of standard deviation {train_config.action_noise:g} on its actions"
        print(f"training on carried episodes: {train_config.batch} per seed, each update one window of "
              f"{task.dynamics.horizon} steps from where they stand{extras}, {begun.trainer.updates_per_epoch} updates "
              f"an epoch (--episodes off: one window from fixed starts)")
    if len(seeds) > 1:
        from stablebptt.engine.config import seed_batching
        print(f"{len(seeds)} seeds in one program, " + (
            "batched (vmap; --seed-batching map: one after another, each bit-identical to the seed trained alone)"
            if seed_batching(train_config) == "vmap" else "one after another (map), each bit-identical to the seed trained alone"))
    if (spread := begun.trainer.spread) is not None:
        devices = ", ".join(str(device) for device in spread.mesh.devices.flat)
        print(f"each update's {train_config.batch} states per seed split over {spread.count} devices ({devices}), "
              "the parameters whole on each")
    if start_epoch == train_config.epochs and resuming:
        print(f"done already: {task_label}, {_epochs(start_epoch)}, final test loss {_final(rows, seeds)} -> {run_dir}")
        return 0

    from stablebptt.cli import EpochProgress, in_worker_thread, out_of_memory, stop_on_signals
    progress = EpochProgress(started, train_config.epochs, start_epoch, begun.trainer.updates_per_epoch,
                             f"{task_label} {train_config.mode}", args.no_progress)
    try:
        # Before its first epoch has begun a run has nothing to save: a signal then stops it at once.
        before_training = lambda: None if progress.compiled else (  # noqa: E731
            f"stopped before this start's first epoch, nothing trained lost: --resume {run_dir} continues the run")
        with stop_on_signals(progress.write, before_training) as should_stop:
            outcome = in_worker_thread(lambda: epochs.train_epochs(*begun.training_arguments(), progress.on_epoch,
                                                                   progress.on_compiled, should_stop, run.owner,
                                                                   begun.program_key, begun.lowered, started,
                                                                   begun.phases, begun.compile_saved_mark))
    except StorageError as error:
        fail(f"{error.strerror}; {_kept(run_dir)}: free space and continue with --resume {run_dir}", code=1)
    except jax.errors.JaxRuntimeError as error:
        if (line := out_of_memory(error)) is None:
            raise
        advice = _less_memory(task_config, train_config, run_dir, task.dynamics.horizon)
        fail(f"{task_label}: {line}; {_kept(run_dir)}: {advice}", code=1)
    progress.close()
    if outcome.status == "diverged":
        print(f"error: {outcome.message}", file=sys.stderr)
        return 1
    if outcome.status == "interrupted":
        print(outcome.message, file=sys.stderr)
        return should_stop.exit_code
    if outcome.status == "budget":
        print(outcome.message)
    from stablebptt.reports.plots import plot_run
    plot_run(run_dir)
    if outcome.state.log_std is not None:
        deviations = np.exp(np.concatenate([np.ravel(leaf) for leaf in jax.tree.leaves(outcome.state.log_std)]))
        print(f"the actions' noise, learned: deviations {deviations.min():.3g} to {deviations.max():.3g} over "
              f"actions and seeds (from {train_config.action_noise:g})")
    print(f"done: {task_label}, mode {train_config.mode}, {_epochs(outcome.epoch)}, final test loss "
          f"{_final(outcome.rows, seeds)} -> {run_dir}")
    return 0


def _kept(run_dir: Path) -> str:
    """What a run stopped by a fault keeps, in words: its last checkpoint, or none yet (its resume starts again)."""
    from stablebptt.runs.run_folder import CHECKPOINT_FILE
    if (run_dir / CHECKPOINT_FILE).is_file():
        return "the run keeps its last checkpoint"
    return "the run has no checkpoint yet (a resume starts it from epoch 0)"


def _less_memory(task_config, train_config: TrainConfig, run_dir: Path, horizon: int) -> str:
    """What a run out of device memory may do, in its own numbers: continue once memory is freed, or spread over
    more of the devices JAX sees (what --resume may change); else a new run that holds fewer states at once."""
    import jax

    from stablebptt.engine.config import seed_batching
    from stablebptt.engine.spread import device_count, splits_evenly
    visible, spanned = len(jax.devices()), device_count(train_config)
    wider = max((count for count in range(spanned + 1, visible + 1) if splits_evenly(train_config.batch, count)),
                default=None)
    more_devices = f" --devices {wider} (its states split over {wider} of the {visible} devices JAX sees)" \
        if wider else ""
    smaller = [f"a smaller --batch (each update rolls {train_config.batch} states per seed for {horizon} steps)"]
    if hasattr(task_config, "steps") and horizon > 1:  # the option that sets those steps
        smaller.append("fewer --steps")
    if train_config.seeds > 1 and seed_batching(train_config) == "vmap":
        smaller.append(f"--seed-batching map (its {train_config.seeds} seeds one after another)")
    if getattr(task_config, "physics_step_residuals", None) == "stored":
        smaller.append("--physics-step-residuals recomputed")
    options = ", ".join(smaller[:-1]) + (" or " if len(smaller) > 1 else "") + smaller[-1]
    return (f"free memory (another process may hold it) and continue with --resume {run_dir}{more_devices}, or "
            f"start a new run with {options}")


def _final(rows, seeds) -> str:
    """The final test loss over the seeds scored (a seed stopped apart has no final numbers)."""
    if not len(rows):
        return "nan"
    mean, std = metrics.final_mean_std(rows)
    scored = int(np.isfinite(metrics.final_values(rows)).sum())
    if scored < len(seeds):
        return f"{mean:.4g} +- {std:.4g} over {scored} of {len(seeds)} seeds"
    return f"{mean:.4g} +- {std:.4g} over {len(seeds)} seeds" if len(seeds) > 1 else f"{mean:.4g}"


def _epochs(count: int) -> str:
    return f"{count} epoch{'' if count == 1 else 's'}"


if __name__ == "__main__":
    from stablebptt.cli import stop_at_once_on_signals
    stop_at_once_on_signals()
    sys.exit(main(sys.argv[1:]))
