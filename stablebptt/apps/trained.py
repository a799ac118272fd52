"""A trained run folder (a single run or a sweep cell) reopened: its task rebuilt, its policies
loaded and rolled out from the run's own test states.

    trained = open_trained(Path("runs/cartpole_3-20261122-101500"))
    states, controls, losses = rollouts_from_test_states(trained.task, trained.train, trained.seed_params(0), 3)
    episode = episodes_from_test_states(trained.task, trained.task.episodes, trained.seed_params(0), trained.train, 3)
"""
from __future__ import annotations

import functools
import inspect
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, NamedTuple

from stablebptt.cli import build
from stablebptt.engine.compiling import compiler_options, large_step
from stablebptt.engine.config import RECORDED_BEFORE, TrainConfig
from stablebptt.engine.episodes import Carried, Episodes, start_window, window_dynamics
from stablebptt.engine.task import Task
from stablebptt.engine.initial_states import sample_states
from stablebptt.errors import InputError
from stablebptt.runs import model_store, run_folder
from stablebptt.runs.session import task_of
from stablebptt.tasks import canonical, entries, entry


def config_for_reopening(module: Any, config: Any, resolved: dict) -> Any:
    """The configuration that rebuilds a trained run's task: its module's ``for_reopening(config, resolved)``,
    or ``for_reopening(config)`` where a module of the user's keeps the hook's first form (the run's record
    not yet passed), or ``config`` itself where the module has none."""
    hook = getattr(module, "for_reopening", None)
    if hook is None:
        return config
    try:
        signature = inspect.signature(hook)
        signature.bind(config, resolved)
    except TypeError:  # takes the configuration alone
        return hook(config)
    except ValueError:  # no signature to read (a builtin): the current form
        pass
    return hook(config, resolved)


@dataclass(frozen=True)
class ReopenedRun:
    """A run folder reopened: what it holds, ready to use (``open_trained``'s answer).

    Attributes:
      run_dir: the folder.
      task_name: its registry name; ``task_config``, ``train``: its configurations.
      task: the task rebuilt from them (from the run's own model copy if the file moved).
      params: the parameters of every seed (leading axis: seed).
      label: the configuration in a few words, with mode and epochs trained.
    """

    run_dir: Path
    task_name: str
    task_config: Any
    train: TrainConfig
    task: Task
    params: Any
    label: str

    def seed_params(self, seed_index: int) -> Any:
        """The parameters of the seed ``train.seed + seed_index``."""
        import jax
        import numpy as np
        if not 0 <= seed_index < self.train.seeds:
            raise InputError(f"seed index {seed_index}: the run has {self.train.seeds} seed(s), 0 to {self.train.seeds - 1}")
        return jax.tree.map(lambda leaf: np.asarray(leaf)[seed_index], self.params)


# The name this class had before; ``stablebptt.Trained`` is what ``train`` returns (stablebptt.engine.fitting).
Trained = ReopenedRun


def configs_of(run_dir: Path, record: dict, train_changes: dict | None = None,
               note: Callable[[str], None] = lambda line: print(line, file=sys.stderr)) -> tuple[Any, TrainConfig]:
    """(task config, train config) of the run in ``run_dir`` whose config.json is ``record``.

    The task config points at the run's own model copy when the model file has moved (``note`` is
    told); ``train_changes`` (e.g. more epochs) are applied to the train config.

    Raises:
      InputError: an unknown task, values of the wrong type, or a model file changed since the run.
    """
    source = str(Path(run_dir) / run_folder.CONFIG_FILE)
    if canonical(record["task"]) not in entries():
        raise InputError(f"{source} names the task {record['task']!r}, which is none of {', '.join(sorted(entries()))}")
    module = entry(record["task"]).load()
    task_values = dict(record["task_config"])
    model_file, moved = model_store.model_to_reopen(Path(run_dir), record)
    if model_file is not None and "model" in task_values:
        task_values["model"] = model_file
        if moved:
            note(moved)
    task_config = build(module.Config, task_values, source)
    if recorded := getattr(module, "recorded_config", None):  # a default that changed since the run began
        task_config = recorded(task_config, record)
    return task_config, build(TrainConfig, {**RECORDED_BEFORE, **record["train"], **(train_changes or {})}, source)


def open_trained(run_dir: Path, note: Callable[[str], None] = lambda line: print(line, file=sys.stderr)) -> ReopenedRun:
    """Reopen a run folder: config checked, task rebuilt, parameters loaded. Switches JAX to the
    run's precision (``train.x64``, ``train.matmul_precision``), so call it before creating arrays of your own.

    Raises:
      InputError: not a run folder, an unknown task, a damaged or missing parameter file, or a
        model file that changed since the run (``note`` is told when the run's copy stands in
        for a file that moved).
    """
    import jax

    run_dir = Path(run_dir)
    record = run_folder.open_run(run_dir)
    task_config, train = configs_of(run_dir, record, note=note)
    task_entry = entry(record["task"])
    if not (run_dir / run_folder.PARAMS_FILE).is_file():
        raise InputError(f"{run_dir} has no {run_folder.PARAMS_FILE}: the run has not finished an epoch yet")
    jax.config.update("jax_enable_x64", train.x64)  # before any array, as the run was trained
    jax.config.update("jax_default_matmul_precision", train.matmul_precision)
    module = task_entry.load()
    resolved = record.get("resolved_task", {})
    task = task_of(module, config_for_reopening(module, task_config, resolved), resolved)
    rebuilt, recorded = (part.get("reward_smoothing") or "none" for part in (task.resolved, resolved))
    # Where the record keeps the surrogate's choices the rebuild takes them: its words may be of another release.
    chosen_alike = "reward_smoothing_choices" in resolved and task.resolved.get(
        "reward_smoothing_choices") == resolved["reward_smoothing_choices"]
    if rebuilt != recorded and not chosen_alike:
        note(f"{run_dir}: the reward's surrogate was rebuilt otherwise than the run trained it ({rebuilt}; "
             f"the run: {recorded})")
    keys = jax.random.split(jax.random.PRNGKey(0), train.seeds)
    template = jax.vmap(lambda key: task.init_params(key, train.zero_output))(keys)
    params = run_folder.load_params(run_dir / run_folder.PARAMS_FILE, template)
    try:  # the epochs params.npz holds: fewer than configured when the run was stopped early
        trained_epochs = int(max(row['epoch'] for row in run_folder.read_metrics(run_dir / run_folder.METRICS_FILE)))
        epochs = f", {trained_epochs} epoch{'s' if trained_epochs != 1 else ''}"
    except (OSError, ValueError, KeyError, TypeError):
        epochs = ""
    label = f"{task_entry.label(task_config)}, mode {train.mode}{epochs}"
    return ReopenedRun(run_dir, canonical(record["task"]), task_config, train, task, params, label)


def _test_states(task: Task, train: TrainConfig, count: int):
    """The first ``count`` test states of the run, drawn exactly as training drew them, and the XLA options of
    a program that steps them."""
    import jax

    _, test_key = jax.random.split(jax.random.PRNGKey(train.data_seed))  # make_trainer's split of the data seed
    initial = jax.tree.map(lambda a: a[:count], sample_states(task, test_key, train.test_size))
    return initial, compiler_options(large_step(task, train, jax.tree.map(lambda a: a[0], initial)))


def _with_initial(initial: Any, states: Any) -> Any:
    """States [N, T, ...] with the initial states [N, ...] put first: [N, T+1, ...]."""
    import jax
    import jax.numpy as jnp
    return jax.tree.map(lambda x0, xs: jnp.concatenate([x0[:, None], xs], axis=1), initial, states)


def rollouts_from_test_states(task: Task, train: TrainConfig, params: Any, count: int):
    """States [N, T+1, ...] (the initial state first), controls [N, T, ...] and losses [N] of the policy
    ``params`` from the first ``count`` test states, drawn exactly as training drew them."""
    import jax
    import numpy as np

    from stablebptt.flows.gradients import reference_rollout

    initial, options = _test_states(task, train, count)

    @functools.partial(jax.jit, compiler_options=options)
    def run(params, initial):
        trajectory = jax.vmap(lambda x0: reference_rollout(task.dynamics, params, x0))(initial)
        losses = jax.vmap(task.dynamics.loss)(trajectory.states, trajectory.controls)
        return _with_initial(initial, trajectory.states), trajectory.controls, losses

    states, controls, losses = jax.device_get(run(params, initial))
    return states, controls, np.asarray(losses)


class Episode(NamedTuple):
    """Whole episodes of a policy (``episodes_from_test_states``' answer)."""

    states: Any  # [N, T+1, ...], the initial state first; after an episode's end, its last state before it
    controls: Any  # [N, T, ...]
    returns: Any  # [N]: the sum of each episode's rewards (undiscounted), as the run's evaluation reports it
    lengths: Any  # [N]: the steps each episode ran, T unless it ended (done) before


def episodes_from_test_states(task: Task, episodes: Episodes, params: Any, train: TrainConfig, count: int,
                              steps: int = 0) -> Episode:
    """Whole episodes of the deterministic policy ``params`` from the first ``count`` test states (fresh starts of
    episodes, drawn exactly as training drew them): ``steps`` steps each (0: ``episodes.length``; an episode
    ends at its length or where done, its last state held from there), its return the sum of the rewards of
    ``episodes.step``, as an environment's evaluation sums them."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from stablebptt.flows.dynamics import Dynamics
    from stablebptt.flows.gradients import reference_rollout

    steps = steps or episodes.length
    initial, options = _test_states(task, train, count)
    step = episodes.step or task.dynamics.step
    rolled = window_dynamics(Dynamics(step=step, policy=task.dynamics.policy, loss=task.dynamics.loss, horizon=steps),
                             episodes, steps)
    reward_dtype = jax.eval_shape(episodes.reward, jax.tree.map(lambda a: a[0], initial)).dtype

    @functools.partial(jax.jit, compiler_options=options)
    def run(params, initial):
        start = start_window(Carried(initial, jnp.zeros(jax.tree.leaves(initial)[0].shape[0], jnp.int32), None),
                             reward_dtype)
        trajectory = jax.vmap(lambda x0: reference_rollout(rolled, params, x0))(start)
        windows = trajectory.states
        return (_with_initial(initial, windows.state), trajectory.controls, windows.reward.sum(axis=1),
                windows.clock[:, -1])

    states, controls, returns, lengths = jax.device_get(run(params, initial))
    return Episode(states, controls, np.asarray(returns), np.asarray(lengths))


def first_nonfinite_step(states: Any) -> list[int]:
    """Per rollout of ``states`` ([N, T+1, ...] leaves), the first step with a number that is not
    finite, or -1 where every step is finite."""
    import jax
    import numpy as np
    finite = np.stack([np.isfinite(np.reshape(a, a.shape[:2] + (-1,))).all(axis=-1)
                       for a in jax.tree.leaves(states)]).all(axis=0)  # [N, T+1]
    return [int(np.argmin(row)) if not row.all() else -1 for row in finite]
