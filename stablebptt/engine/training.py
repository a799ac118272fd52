"""The training engine: one compiled epoch, seeds vmapped into one program.

``make_trainer(task, config)`` does the static set-up (flows, optimizer, data,
the plan of how to differentiate the task) and returns pure functions;
``stablebptt.runs.run_folder`` drives them epoch by epoch.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.extend
import jax.numpy as jnp
import optax

from stablebptt.engine.checks import check_task, evaluated
from stablebptt.engine.compiling import compiler_options, run_plan, step_size
from stablebptt.engine.config import (LARGE_STEP, TrainConfig, check_batches, eval_cadence, require_train_config,
                                      seed_batching)
from stablebptt.engine.critic import bootstrap, fit_to_window, init_critic
from stablebptt.engine.episodes import (
    Episodes,
    Exploring,
    bounded_log_std,
    continue_from,
    cut_short,
    cut_sooner,
    entropy_gradient,
    first_population,
    initial_log_std,
    refill_pool,
    skipping,
    start_window,
    updates_per_epoch,
    window_dynamics,
)
from stablebptt.engine.initial_states import InitialStates, draw_initial_states, drawn_counts
from stablebptt.engine.optimizer import adam, make_grid_optimizer, make_optimizer
from stablebptt.engine.per_update import PerUpdateEpoch, compile_side_by_side
from stablebptt.engine.program_store import kept_answer
from stablebptt.engine.spread import Spread, split, split_where_even, spread_of
from stablebptt.engine.task import Task
from stablebptt.errors import InputError, config_field
from stablebptt.flows.dynamics import Plan
from stablebptt.flows.gradients import flow_window, reference_loss, reference_losses
from stablebptt.flows.modes import FLOWS, flows_needed, tree_cosine

PyTree = Any


class TrainState(NamedTuple):
    params: PyTree
    opt_state: PyTree
    carried: PyTree = None  # training on episodes: the population carried from update to update (``Carried``)
    critic: PyTree = None  # with ``TrainConfig.critic``: the learned value at a window's end (``Critic``)
    # With ``TrainConfig.learn_action_noise``: the log deviation of each action's noise (shaped as an action),
    # updated with the parameters by one optimizer (``opt_state`` is then that of ``Exploring``).
    log_std: PyTree = None


class UpdateOutput(NamedTuple):
    """What one update reports of itself (per seed; stacked over an epoch's updates)."""

    loss: jax.Array  # the window's loss (training on episodes: its negative return)
    update_norm: jax.Array  # the global norm of the update applied
    cosine: jax.Array  # cosine of g_M and g_R (NaN where they are not both computed)
    flows_finite: jax.Array  # bool [flows]: each computed flow's gradient finite
    taken: jax.Array  # bool: the update ran (an epoch cut short skips the rest: ``Trainer.epoch_batches``)


class Initializer(NamedTuple):
    """``init(seeds) -> TrainState`` in two programs: the policy's parameters, the learned noise's deviations
    and their optimizer state, whose values may wait for a task's check still running (``Task.settle``),
    and the rest (the carried population's resets, the critic), which waits for nothing:
    ``starting.prepare`` compiles it beside the epoch."""

    policy: Callable[[jax.Array], tuple[PyTree, PyTree, PyTree]]  # seeds [S] -> (params, opt_state, log_std)
    rest: Callable[[jax.Array], tuple[PyTree, PyTree]]  # seeds [S] -> (carried, critic)

    def __call__(self, seeds: jax.Array) -> TrainState:
        params, opt_state, log_std = self.policy(seeds)
        return TrainState(params, opt_state, *self.rest(seeds), log_std)


class Trainer(NamedTuple):
    """Compiled pieces of a run. Every function maps over a leading seed axis.

    Where ``compiler_options`` is set (on a GPU; on a CPU for a large step) the functions are
    programs of their own: call, ``lower`` or ``trace`` them, but JAX refuses them inside another
    jit, ``scan`` or ``make_jaxpr``.
    """

    flows: tuple[str, ...]
    init: Initializer  # seeds [S] -> states
    # (states, batches, train, test) -> states, metrics [S]; a grid trainer takes
    # (states, values, batches, train, test), values [S] of the task's cell option (None if it has none).
    epoch: Callable[..., tuple[TrainState, dict]]
    evaluate: Callable[[PyTree, PyTree], jax.Array]  # (params [S], initial states) -> loss [S]
    initial_states: InitialStates  # ``train_states`` and ``test_states``, and their shapes for lowering
    batches: PyTree
    plan: Plan  # how every function differentiates and rolls out the task
    compiler_options: dict | None = None  # XLA options every program of the trainer is compiled with
    episodes: Episodes | None = None  # the episodes it carries (``TrainConfig.episodes``); None: fixed starts
    # With ``evaluation`` (training on episodes, unless every epoch is evaluated) ``epoch`` runs the updates
    # alone, its train and test losses NaN; ``evaluation(params, train, test) -> metrics [S]`` gives them
    # (``train_loss``, ``test_loss``, ``finite``, ``nonfinite``) as a program of its own, run on a cadence.
    evaluation: Callable[..., dict] | None = None
    horizon: int = 0  # steps of a training rollout (training on episodes: of a window)
    spread: Spread | None = None  # the devices its programs span (``TrainConfig.devices``); None: one
    # Training on episodes, the program every epoch starts with: ``refill(states) -> states`` with the fresh
    # states that epoch's ended episodes start from drawn into the carried pool (``fresh``). A program of its
    # own, compiled beside the epoch's, not a branch of its first update: there it compiled a second
    # simulator (an environment's reset) into the epoch's program and slowed every update (docs/performance.md,
    # "The update against its floor").
    refill: Callable[[TrainState], TrainState] | None = None

    @property
    def train_states(self) -> PyTree:
        """The training initial states (waiting for them where they are still being drawn)."""
        return self.initial_states.drawn.result()[0]

    @property
    def test_states(self) -> PyTree:
        """The test initial states (waiting for them where they are still being drawn)."""
        return self.initial_states.drawn.result()[1]

    @property
    def updates_per_epoch(self) -> int:
        return len(jax.tree.leaves(self.batches)[0])

    def epoch_batches(self, updates: int | None = None) -> PyTree:
        """The batches of an epoch of its first ``updates`` (None: all): ``episodes.cut_short``."""
        if updates is None or updates >= self.updates_per_epoch:
            return self.batches
        if self.episodes is None:
            raise InputError("an epoch is cut short only where it trains on episodes")
        return cut_short(self.batches, updates)

    def fresh(self, state: TrainState) -> TrainState:
        """``state`` as an epoch starts from it: training on episodes, its pool refilled (``refill``)."""
        return state if self.refill is None else self.refill(state)

    def kept_under(self, program_key: dict | None) -> dict | None:
        """The key its epoch is kept under between runs (``program_store``): none where it is spread
        over devices, whose placement a kept program would lose."""
        return None if self.spread is not None else program_key


def make_trainer(task: Task, config: TrainConfig, grid: bool = False, plan: Plan | None = None,
                 keep: dict | None = None, lap: Callable[[str], None] | None = None) -> Trainer:
    """Static set-up of a run: data, flows, optimizer, plan; returns jitted pure functions.

    With ``grid=True`` every seed slot is a sweep cell: all flows are computed,
    the optimizer of ``make_grid_optimizer`` selects each cell's update, and
    ``epoch`` takes each cell's value of ``task.cell_option`` as its second argument.
    The plan (``Trainer.plan``) is ``run_plan``'s, or ``plan`` whole where one is given.
    With ``keep`` (everything that decides the run's programs: ``program_store``), the task check's,
    the step size's and the memory plan's traced measurements are kept, and an identical later run
    skips them. ``lap(name)``, where given, is called as each part of the set-up ends (a start's phases:
    ``starting.prepare``).
    """
    lap = lap or (lambda name: None)
    require_train_config(config)
    if config.x64 and not jax.config.jax_enable_x64:
        raise InputError(f"{config_field(config, 'x64')} asks for float64, but JAX runs in float32: stablebptt.train "
                         "trains such a config in float64 by itself; with make_trainer, build the trainer and call "
                         "its functions under `with jax.enable_x64(True):`")
    kept = functools.partial(kept_answer, keep)
    kept("task checked", lambda: check_task(task, config.zero_output, drawn_counts(config)) or True)
    lap("trainer set-up: task check")
    if plan is not None and not isinstance(plan, Plan):
        raise InputError(f"make_trainer's plan must be a stablebptt.Plan or None, got {type(plan).__name__}")
    episodes = episodes_of(task, config)
    flows = FLOWS if grid else flows_needed(config.mode, config.cosine)
    optimizer = make_grid_optimizer(config) if grid else make_optimizer(config, flows)

    spread = spread_of(config)
    # Carried episodes draw their initial states only to evaluate, so those are drawn while the set-up and
    # the epoch's trace go on, from their shapes alone (an environment's reset compiles and runs a large
    # program: the cheetah's settles each state for 200 physics steps); fixed starts are the batches.
    initial = draw_initial_states(task, config, deferred=episodes is not None and spread is None)
    lap("trainer set-up: initial states")
    # Shapes only (the plan and the step's size are traced, never run): no eager slice of every leaf,
    # which on a GPU compiles one program per leaf shape.
    example_state = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape[1:], a.dtype, weak_type=getattr(a, "weak_type", False)), initial.shapes[0])
    # One trace of one step, kept too: its size, and whether it solves for constraints (a loop).
    operations, solves = kept("step size", lambda: list(step_size(task, config, example_state)))
    large = operations > LARGE_STEP
    options = compiler_options(large)
    jit = functools.partial(jax.jit, compiler_options=options, **(spread.jit_options() if spread else {}))
    measured = lambda name, measure: kept(f"traced bytes, {name}", measure)  # noqa: E731
    plan = run_plan(task, config, example_state, large, measured) if plan is None else plan  # one for every dynamics an epoch uses
    lap("trainer set-up: step's trace and memory plan")
    if spread is not None and plan.jacobian_chunk:  # a loop over chunks would hold every device's examples on each
        plan = dataclasses.replace(plan, chunk_placement=functools.partial(split_where_even, spread))
    if episodes is None:
        # Fixed order, no shuffling: minibatch i is always the same states.
        batches = jax.jit(lambda states: jax.tree.map(  # one program, not one eager reshape per leaf
            lambda a: a.reshape((config.train_size // config.batch, config.batch) + a.shape[1:]), states))(
                initial.drawn.result()[0])
    else:  # the updates of an epoch take the carried states: the scan runs over their numbers alone
        window = task.dynamics.horizon
        batches = jnp.arange(updates_per_epoch(task.episodes, window))  # the task's episode, however soon cut
        reward_dtype = jax.eval_shape(episodes.reward, example_state).dtype
        # Known columns index the task's state; a window's state holds more. The window's own plan drops them.
        window_plan = dataclasses.replace(plan, known_columns=None)
        if config.critic:
            critic_optimizer = adam(config, config.critic_lr)
            observations = jax.eval_shape(episodes.observe, example_state).shape[0]
    if spread is not None:  # the same every epoch: moved to every device once
        train_states, test_states, batches = spread.placed((*initial.drawn.result(), batches))
        initial = InitialStates.at_hand(train_states, test_states)

    def init_policy(seed):
        params = task.init_params(jax.random.PRNGKey(seed), config.zero_output)
        if not config.learn_action_noise:
            return params, optimizer.init(params), None
        log_std = initial_log_std(jax.eval_shape(task.dynamics.policy, params, example_state), config.action_noise)
        return params, optimizer.init(Exploring(params, log_std)), log_std

    def init_rest(seed):
        key = jax.random.PRNGKey(seed)
        carried = None if episodes is None else first_population(key, episodes, config.batch, window)
        critic = (init_critic(key, observations, critic_optimizer, (config.critic_width,) * config.critic_depth,
                              config.normalize_critic_observations, config.critics)
                  if config.critic else None)
        return carried, critic

    def evaluate(params, initial_states, dynamics=task.dynamics):
        if task.evaluation is not None:
            return evaluated(task, params, initial_states).mean()
        return reference_loss(dynamics, params, initial_states, plan=plan)

    def update(dynamics, state, batch):
        critic = state.critic
        differentiated = state.params if state.log_std is None else Exploring(state.params, state.log_std)
        if episodes is None:
            loss, grads, _, visited = flow_window(dynamics, flows, state.params, split(spread, batch), plan)
            carried, counted = None, jnp.ones(jax.tree.leaves(visited)[0].shape[:2], bool)
        else:  # one window from where the carried states stand; the gradient stops at its start
            at_end = None if critic is None else bootstrap(critic, episodes.observe)
            carried = _split_population(spread, state.carried)  # its pool refilled as the epoch began (refill)
            window_result = flow_window(window_dynamics(dynamics, episodes, window, at_end, config.action_noise,
                                                        config.learn_action_noise, config.value_at_time_limit,
                                                        config.value_at_gradient_cut),
                                        flows, differentiated,
                                        start_window(carried, reward_dtype, config.action_noise > 0,
                                                     config.value_at_time_limit), window_plan)
            loss, grads = window_result.loss, window_result.grads
            if config.entropy:
                grads = grads._replace(log_std=jax.tree.map(
                    jnp.add, grads.log_std, entropy_gradient(state.log_std, episodes.discount, window, config.entropy)))
            visited, counted = window_result.visited.state, window_result.visited.running
            carried = continue_from(window_result.final, carried)
            if critic is not None:
                critic = fit_to_window(critic, window_result.visited, window_result.final, episodes.observe,
                                       episodes.discount, config.td_lambda, critic_optimizer)
        updates, opt_state = optimizer.update(grads, state.opt_state, differentiated)
        params, log_std = optax.apply_updates(differentiated, updates), None
        if state.log_std is not None:
            params, log_std = params.policy, bounded_log_std(params.log_std)
        if task.refresh_statistics is not None:  # what the policy saw in this window, after the update that used it
            params = task.refresh_statistics(params, visited, counted)
        if "M" in flows and "R" in flows:
            row = lambda f: jax.tree.map(lambda a: a[flows.index(f)], grads)
            cosine = tree_cosine(row("M"), row("R"))
        else:
            cosine = jnp.full((), jnp.nan, loss.dtype)
        # Every flow's gradient, not only the update: mode C's sign agreement
        # turns a NaN of g_R into a finite zero update.
        flows_finite = jnp.stack([_all_finite(jax.tree.map(lambda a, i=i: a[i], grads)) for i in range(len(flows))])
        return TrainState(params, opt_state, carried, critic, log_std), UpdateOutput(loss, optax.tree.norm(updates), cosine,
                                                                            flows_finite, jnp.array(True))

    def evaluate_both(params, train_states, test_states, dynamics=task.dynamics):
        # Training and test states in one rollout: the program holds one copy of the simulator, not two.
        both = split_where_even(spread, jax.tree.map(lambda a, b: jnp.concatenate([a, b]), train_states, test_states))
        if task.evaluation is not None:
            return evaluated(task, params, both)
        return reference_losses(dynamics, params, both, plan=plan)

    metrics = EpochMetrics(config)

    def evaluation_metrics(params, train_states, test_states):
        return metrics.of_evaluation(evaluate_both(params, train_states, test_states))

    # Training on episodes, an evaluation rolls whole episodes from fresh resets: compiled apart and run on
    # a cadence (TrainConfig.eval_every) it costs a fraction of the run, where inside every epoch it may cost most.
    apart = not grid and eval_cadence(config, episodes is not None)[0] != "epoch"

    def epoch(state, batches, train_states, test_states, dynamics=task.dynamics):
        one, real = functools.partial(update, dynamics), jnp.result_type(float)  # float64 under x64
        skipped = UpdateOutput(loss=jnp.zeros((), real), update_norm=jnp.zeros((), real),
                               cosine=jnp.full((), jnp.nan, real), flows_finite=jnp.ones(len(flows), bool),
                               taken=jnp.array(False))
        state, per_update = jax.lax.scan(one if episodes is None else skipping(one, skipped), state, batches)
        losses = None if apart else evaluate_both(state.params, train_states, test_states, dynamics)
        return state, metrics.of_epoch(state, per_update, losses)

    def grid_epoch(state, value, batches, train_states, test_states):
        dynamics = task.dynamics if value is None else task.cell_option.dynamics(value)
        return epoch(state, batches, train_states, test_states, dynamics)

    def refill(state):
        return state._replace(carried=_split_population(spread, refill_pool(state.carried, episodes)))

    over_seeds = functools.partial(_over_seeds, seed_batching(config))

    if grid:
        epoch_program = jit(over_seeds(grid_epoch, mapped=2))
    elif config.epoch_program == "whole" or config.epoch_program == "auto" and not (
            large or solves and compile_side_by_side()):
        epoch_program = jit(over_seeds(epoch))
    else:
        epoch_program = PerUpdateEpoch(jit(over_seeds(functools.partial(update, task.dynamics))),
                                       None if apart else jit(over_seeds(evaluate_both)),
                                       jit(over_seeds(metrics.of_epoch, mapped=3 if not apart else 2)),
                                       numbered=episodes is not None)
    return Trainer(
        flows=flows,
        init=Initializer(jit(over_seeds(init_policy)), jit(over_seeds(init_rest))),
        epoch=epoch_program,
        evaluate=jit(over_seeds(evaluate)),
        initial_states=initial,
        batches=batches,
        plan=plan,
        compiler_options=options,
        episodes=episodes,
        evaluation=jit(over_seeds(evaluation_metrics)) if apart else None,
        horizon=task.dynamics.horizon,
        spread=spread,
        refill=None if episodes is None else jit(over_seeds(refill)),
    )


def _split_population(spread: Spread | None, carried: Any) -> Any:
    """A carried population's states, clocks and pool split by env over ``spread``'s devices (its key
    and its pool's count stay whole)."""
    if spread is None:
        return carried
    return carried._replace(states=split(spread, carried.states), clocks=split(spread, carried.clocks),
                            pool=split(spread, carried.pool))


def _over_seeds(batching: str, function: Callable, mapped: int = 1) -> Callable:
    """``function(*per_seed, *shared)`` mapped over the leading seed axis of its first ``mapped`` arguments."""
    if batching == "vmap":
        return lambda *args: jax.vmap(lambda *per_seed: function(*per_seed, *args[mapped:]))(*args[:mapped])
    # lax.map compiles the single-seed program once and loops it, so each
    # seed's numbers are bit-identical to that seed trained alone; XLA fuses
    # batched physics differently, which moves the last bits under vmap.
    return lambda *args: jax.lax.map(lambda per_seed: function(*per_seed, *args[mapped:]), args[:mapped])


class EpochMetrics:
    """One seed's metrics of an epoch (``of_epoch``) and of an evaluation made apart (``of_evaluation``),
    each with its checks: the ``finite`` flag that stops training and the ``nonfinite`` bits that name
    what failed (``nonfinite_names``)."""

    def __init__(self, config: TrainConfig):
        self.train_size, self.stop_on_flows = config.train_size, config.nonfinite_flows == "stop"

    def _losses(self, losses_of_both):
        """The train and test losses (means over their states) and whether each is finite."""
        train_loss, test_loss = losses_of_both[:self.train_size].mean(), losses_of_both[self.train_size:].mean()
        return train_loss, test_loss, [jnp.isfinite(train_loss), jnp.isfinite(test_loss)]

    def _checked(self, checks):
        """(every failed check's bit, those that stop training), the checks in ``CHECK_NAMES``' order."""
        failed = sum(jnp.where(ok, 0, 1 << bit) for bit, ok in enumerate(checks))
        # With nonfinite_flows "zero" a flow's non-finite gradient (C's update stays finite) is named, not a stop.
        return failed, failed if self.stop_on_flows else failed & ((1 << FLOW_BITS) - 1)

    def of_epoch(self, state: TrainState, per_update: UpdateOutput, losses_of_both=None) -> dict:
        """The epoch's metrics from its updates' outputs ([updates] each) and every state's loss (None: not
        evaluated in this epoch, its train and test losses NaN)."""
        if losses_of_both is None:
            train_loss = test_loss = jnp.full((), jnp.nan, per_update.loss.dtype)
            loss_ok = [jnp.array(True), jnp.array(True)]
        else:
            train_loss, test_loss, loss_ok = self._losses(losses_of_both)
        # The optimizer state too: an overflowed Adam moment (v = inf) silently zeroes every later update.
        # The carried states are not checked: a task's state may hold infinities by design; their losses tell.
        # An epoch cut short counts the updates it ran alone (``UpdateOutput.taken``).
        taken = per_update.taken
        ran = lambda values: jnp.where(taken, values, 0)  # noqa: E731
        mean = lambda values: ran(values).sum() / jnp.maximum(taken.sum(), 1)  # noqa: E731
        flows_finite = per_update.flows_finite | ~taken[:, None]
        checks = ([jnp.isfinite(ran(per_update.loss)).all(),
                   jnp.isfinite(ran(per_update.update_norm)).all() & _all_finite((state.params, state.opt_state, state.critic))]
                  + loss_ok + list(flows_finite.all(axis=0)))
        failed, stopping = self._checked(checks)
        return {
            "batch_loss": mean(per_update.loss),
            "train_loss": train_loss,
            "test_loss": test_loss,
            "update_norm": mean(per_update.update_norm),
            "cosine": mean(per_update.cosine),
            "finite": stopping == 0,
            "nonfinite": failed,  # bit set per failed check, in the order of nonfinite_names(flows)
            "nonfinite_flow_updates": jnp.sum(~flows_finite.all(axis=1)),  # updates with a non-finite flow gradient
        }

    def of_evaluation(self, losses_of_both) -> dict:
        """The train and test losses of an evaluation made apart from the epoch, with their checks' bits."""
        train_loss, test_loss, loss_ok = self._losses(losses_of_both)
        failed, stopping = self._checked([jnp.array(True)] * 2 + loss_ok)
        return {"train_loss": train_loss, "test_loss": test_loss, "finite": stopping == 0, "nonfinite": failed}


def episodes_of(task: Task, config: TrainConfig) -> Episodes | None:
    """The episodes a run of ``task`` trains on (``TrainConfig.episodes``), or None for the paper's protocol."""
    if config.episodes == "on" and task.episodes is None:
        raise InputError(f"{config_field(config, 'episodes')} on: {task.name} has no episodes to carry (Task.episodes "
                         "gives a reset, a reward, a done and a length); train it with episodes off")
    if config.episodes == "off" or task.episodes is None:
        needs = {"critic": "a learned value at a window's end", "action_noise": "exploration noise on a window's actions", "training_episode_length": "episodes cut sooner in training"}
        for name, what in needs.items():
            if getattr(config, name):
                raise InputError(f"{config_field(config, name)}: {what} needs carried episodes, and {task.name} "
                                 f"trains from fixed starts here (episodes {'off' if task.episodes is not None else 'it has none'})")
        check_batches(config)
        return None
    if config.critic and task.episodes.observe is None:
        raise InputError(f"{config_field(config, 'critic')}: {task.name}'s Episodes has no observe(state), what the critic sees")
    if config.value_at_gradient_cut and task.episodes.gradient_cut is None:
        raise InputError(f"{config_field(config, 'value_at_gradient_cut')}: {task.name}'s step cuts no window's "
                         "derivative to value (an environment cuts where --contact-gradient-cut says)")
    return cut_sooner(task.episodes, config.training_episode_length, config_field(config, "training_episode_length"),
                      task.name) if config.training_episode_length else task.episodes


def _all_finite(tree: PyTree) -> jax.Array:
    leaves = [leaf for leaf in jax.tree.leaves(tree) if jnp.issubdtype(leaf.dtype, jnp.inexact)]
    return jnp.all(jnp.array([jnp.isfinite(leaf).all() for leaf in leaves])) if leaves else jnp.array(True)


# The nonfinite metric's checks before the flows' own, in the order EpochMetrics makes them.
CHECK_NAMES = ("batch loss", "update or optimizer state", "train loss", "test loss")
FLOW_BITS = len(CHECK_NAMES)


def nonfinite_names(flows: tuple[str, ...], failed: int) -> list[str]:
    """What the ``nonfinite`` metric of an epoch says was not finite, in words."""
    names = list(CHECK_NAMES) + [f"gradient of flow {f}" for f in flows]
    return [name for bit, name in enumerate(names) if int(failed) >> bit & 1]


