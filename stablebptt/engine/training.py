"""The training engine: one compiled epoch, seeds vmapped into one program.

``make_trainer(task, config)`` does the static set-up (flows, optimizer, data,
the plan of how to differentiate the task) and returns pure functions;
``stablebptt.runs.run_folder`` drives them epoch by epoch.
"""
from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import math
import numbers
import os
from dataclasses import dataclass, field, fields
from typing import Any, Callable, NamedTuple

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import optax

from stablebptt.engine.checks import check_task, parameter_shapes
from stablebptt.engine.memory import MemoryPlan, measure_now, plan_memory
from stablebptt.engine.program_store import kept_answer
from stablebptt.engine.task import Task
from stablebptt.errors import InputError, config_field
from stablebptt.flows.dynamics import Plan
from stablebptt.flows.gradients import flow_gradients, reference_loss, reference_losses
from stablebptt.flows.modes import (
    FLOWS,
    MODE_TABLE,
    MODES,
    flows_needed,
    select_flow,
    tree_cosine,
)
from stablebptt.timing import usable_cores

PyTree = Any
CLIP_MODES = ("value", "norm", "none")
SEED_BATCHING = ("map", "vmap")
EPOCH_PROGRAMS = ("auto", "whole", "per-update")
# Operations in one traced step above which a scene counts as large: ``epoch_program="auto"``
# compiles it per update, and forward mode pushes all its tangents in one pass. XLA's CPU compiler
# can take many minutes and gigabytes for a program that inlines a contact model's step many times
# (updates, rollouts, one Jacobian pass per input, evaluation), where fewer copies compiled apart
# take a few minutes. The built-in tasks' steps (the cart-poles: about 4,000) are small; so are the
# DeepMind Control Suite's contact scenes whose step is generated (stablebptt/physics/rigid_body.py), while
# through MJX's stages they are large.
LARGE_STEP = 8_000
# XLA:CPU's default fusion emitters compute each element of a fusion by calling the
# functions of its operands, so an operand that many elements read is recomputed for each.
# MJX's kinematics of a deep tree fuse into long elementwise chains: humanoid_CMU's first
# 5-step epoch had not ended after 20 minutes, nearly all of it in one fusion of 623
# operations that yields 24 numbers; with XLA's loop emitter it takes 5-7 s. Small steps
# keep the fusion emitters: their updates run 15-30% faster with them.
LARGE_STEP_CPU_OPTIONS = {"xla_cpu_use_fusion_emitters": False}
MAX_SEED = 2**32 - 1  # seeds are unsigned 32-bit PRNG seeds



@dataclass(frozen=True)
class TrainConfig:
    """Training options shared by every task; the defaults are the paper's."""

    mode: str = field(default="C", metadata={"help": "gradient flow: " + ", ".join(f"{m.name} ({m.description})" for m in MODE_TABLE.values()), "choices": MODES})
    clip: str = field(default="value", metadata={"help": "gradient clipping: value (each element to +-threshold), norm (global norm), none", "choices": CLIP_MODES})
    clip_threshold: float = field(default=1.0, metadata={"help": "threshold of value and norm clipping"})
    epochs: int = field(default=1000, metadata={"help": "number of passes over the training set"})
    seeds: int = field(default=1, metadata={"help": "independent seeds trained in one compiled program"})
    seed: int = field(default=42, metadata={"help": "first network seed; seed k uses seed+k"})
    lr: float = field(default=1e-3, metadata={"help": "Adam learning rate"})
    batch: int = field(default=8, metadata={"help": "initial states per update"})
    train_size: int = field(default=256, metadata={"help": "training initial states"})
    test_size: int = field(default=256, metadata={"help": "test initial states"})
    data_seed: int = field(default=42, metadata={"help": "seed of the training and test initial states (shared by all network seeds)"})
    zero_output: bool = field(default=True, metadata={"help": "start the output layer at zero as the original run scripts do (--no-zero-output: Glorot)"})
    cosine: bool = field(default=True, metadata={"help": "also compute g_M and g_R in every mode to log their cosine (--no-cosine: only the flows the mode needs)"})
    x64: bool = field(default=False, metadata={"help": "run everything in float64"})
    unroll: int = field(default=1, metadata={"help": "rollout steps per loop iteration (1 is fastest on a CPU; 5-10 on a GPU, see Plan.unroll)"})
    checkpoint_every: int = field(default=1, metadata={"help": "epochs between checkpoints"})
    seed_batching: str = field(default="map", metadata={"help": "how seeds share one program: map (one after another, each bit-identical to the seed trained alone) or vmap (batched: faster per seed, equal to a solo run only to float rounding)", "choices": SEED_BATCHING})
    epoch_program: str = field(default="auto", metadata={"help": "whole: an epoch is one compiled program (fastest for small scenes, and on a GPU); per-update: the epoch loops in Python over one compiled update and one evaluation (large scenes compile in a fraction of the time and memory); auto: per-update for steps of more than " + f"{LARGE_STEP} operations, and on a CPU of several cores for steps with a constraint solver (update and evaluation compile side by side)", "choices": EPOCH_PROGRAMS})

    def __post_init__(self):
        for item in fields(self):  # from Python anything can arrive: 2.5 epochs, lr "0.1", batch None
            value, kind = getattr(self, item.name), item.type if isinstance(item.type, str) else item.type.__name__
            fits = {"int": isinstance(value, numbers.Integral) and not isinstance(value, bool),
                    "float": isinstance(value, numbers.Real) and not isinstance(value, bool),
                    "str": isinstance(value, str), "bool": isinstance(value, (bool, np.bool_))}[kind]
            if not fits:
                raise InputError(f"{config_field(self, item.name)} must be {'a whole number' if kind == 'int' else kind}, "
                                 f"got {value!r}")
        if self.mode not in MODES:
            raise InputError(f"unknown mode {self.mode!r}: choose one of {', '.join(MODES)}")
        if self.clip not in CLIP_MODES:
            raise InputError(f"unknown clip mode {self.clip!r}: choose one of {', '.join(CLIP_MODES)}")
        for name in ("epochs", "seeds", "batch", "train_size", "test_size", "checkpoint_every", "unroll"):
            if getattr(self, name) <= 0:
                raise InputError(f"{config_field(self, name)} must be a positive integer, got {getattr(self, name)}")
        for name in ("lr", "clip_threshold"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"{config_field(self, name)} must be a positive number, got {value}")
        for name, last in (("seed", self.seed + self.seeds - 1), ("data_seed", self.data_seed)):
            if not 0 <= getattr(self, name) <= last <= MAX_SEED:
                raise InputError(f"{config_field(self, name)} must be from 0 to {MAX_SEED}"
                                 + (f" with {config_field(self, 'seeds')} {self.seeds}" if name == "seed" else "")
                                 + f", got {getattr(self, name)}")
        if self.seed_batching not in SEED_BATCHING:
            raise InputError(f"unknown seed batching {self.seed_batching!r}: choose map or vmap")
        if self.epoch_program not in EPOCH_PROGRAMS:
            raise InputError(f"unknown epoch program {self.epoch_program!r}: choose one of {', '.join(EPOCH_PROGRAMS)}")
        if self.train_size % self.batch:
            raise InputError(f"{config_field(self, 'batch')} {self.batch} does not divide the {self.train_size} training "
                             "states: pick a divisor")


class TrainState(NamedTuple):
    params: PyTree
    opt_state: PyTree


# Clip modes as optax transforms of the threshold: single runs and grid cells clip with the same ones.
CLIPPERS = {"value": optax.clip, "norm": optax.clip_by_global_norm, "none": lambda threshold: optax.identity()}


def _switch(transforms: list[optax.GradientTransformation], index: jax.Array) -> optax.GradientTransformation:
    """The update of ``transforms[index]`` for an index known only at run time (stateless transforms)."""
    def update(updates, state, params=None):
        candidates = [transform.update(updates, optax.EmptyState(), params)[0] for transform in transforms]
        return jax.tree.map(lambda *c: jnp.select([index == i for i in range(len(c))], c), *candidates), state

    return optax.GradientTransformation(lambda params: optax.EmptyState(), update)


def make_optimizer(config: TrainConfig, flows: tuple[str, ...], per_cell: bool = False) -> optax.GradientTransformation:
    """ONE chain, for single runs and grid cells alike: the flows reduced to the mode's update ->
    clip -> Adam.

    The learning rate and clip threshold live in the optimizer state
    (``inject_hyperparams``), so a sweep can vmap over them. With ``per_cell``
    (sweeps), the mode and clip mode are numbers there too (indices into
    ``MODES`` and ``CLIP_MODES``), each cell selecting among the same transforms
    a single run chains, so cells of different modes and clip modes vmap into
    one program; ``flows`` must then hold R, M and S. Set the per-cell values in
    ``opt_state.hyperparams`` after ``init``.
    """
    def chain(learning_rate, clip_threshold):
        return optax.chain(select_flow(config.mode, flows), CLIPPERS[config.clip](clip_threshold),
                           optax.adam(learning_rate))

    def chain_per_cell(learning_rate, clip_threshold, mode_index, clip_index):
        return optax.chain(_switch([select_flow(mode, flows) for mode in MODES], mode_index),
                           _switch([CLIPPERS[name](clip_threshold) for name in CLIP_MODES], clip_index),
                           optax.adam(learning_rate))

    if per_cell:
        return optax.inject_hyperparams(chain_per_cell)(
            learning_rate=config.lr, clip_threshold=config.clip_threshold,
            mode_index=MODES.index(config.mode), clip_index=CLIP_MODES.index(config.clip))
    return optax.inject_hyperparams(chain)(learning_rate=config.lr, clip_threshold=config.clip_threshold)


def make_grid_optimizer(config: TrainConfig) -> optax.GradientTransformation:
    """``make_optimizer`` for sweep cells: all flows computed, mode and clip mode per cell."""
    return make_optimizer(config, FLOWS, per_cell=True)


class Trainer(NamedTuple):
    """Compiled pieces of a run. Every function maps over a leading seed axis.

    Where ``compiler_options`` is set (on a GPU; on a CPU for a large step) the functions are
    programs of their own: call, ``lower`` or ``trace`` them, but JAX refuses them inside another
    jit, ``scan`` or ``make_jaxpr``.
    """

    flows: tuple[str, ...]
    init: Callable[[jax.Array], TrainState]  # seeds [S] -> states
    # (states, batches, train, test) -> states, metrics [S]; a grid trainer takes
    # (states, values, batches, train, test), values [S] of the task's cell option (None if it has none).
    epoch: Callable[..., tuple[TrainState, dict]]
    evaluate: Callable[[PyTree, PyTree], jax.Array]  # (params [S], initial states) -> loss [S]
    train_states: PyTree
    test_states: PyTree
    batches: PyTree
    plan: Plan  # how every function differentiates and rolls out the task
    compiler_options: dict | None = None  # XLA options every program of the trainer is compiled with


def make_trainer(task: Task, config: TrainConfig, grid: bool = False, plan: Plan | None = None,
                 keep: dict | None = None) -> Trainer:
    """Static set-up of a run: data, flows, optimizer, plan; returns jitted pure functions.

    With ``grid=True`` every seed slot is a sweep cell: all flows are computed,
    the optimizer of ``make_grid_optimizer`` selects each cell's update, and
    ``epoch`` takes each cell's value of ``task.cell_option`` as its second argument.
    The plan (``Trainer.plan``) is ``run_plan``'s, or ``plan`` whole where one is given.
    With ``keep`` (everything that decides the run's programs: ``program_store``), the task check's,
    the step size's and the memory plan's traced measurements are kept, and an identical later run
    skips them.
    """
    if not isinstance(config, TrainConfig):
        raise InputError(f"expected a stablebptt.TrainConfig, got {type(config).__name__}")
    if config.x64 and not jax.config.jax_enable_x64:
        raise InputError(f"{config_field(config, 'x64')} asks for float64, but JAX runs in float32: stablebptt.train "
                         "trains such a config in float64 by itself; with make_trainer, build the trainer and call "
                         "its functions under `with jax.enable_x64(True):`")
    kept = functools.partial(kept_answer, keep)
    kept("task checked", lambda: check_task(task, config.zero_output) or True)
    if plan is not None and not isinstance(plan, Plan):
        raise InputError(f"make_trainer's plan must be a stablebptt.Plan or None, got {type(plan).__name__}")
    flows = FLOWS if grid else flows_needed(config.mode, config.cosine)
    optimizer = make_grid_optimizer(config) if grid else make_optimizer(config, flows)

    train_key, test_key = jax.random.split(jax.random.PRNGKey(config.data_seed))
    train_states = sample_states(task, train_key, config.train_size)
    test_states = sample_states(task, test_key, config.test_size)
    # Shapes only (the plan and the step's size are traced, never run): no eager slice of every leaf,
    # which on a GPU compiles one program per leaf shape.
    example_state = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape[1:], a.dtype, weak_type=getattr(a, "weak_type", False)), train_states)
    # One trace of one step, kept too: its size, and whether it solves for constraints (a loop).
    operations, solves = kept("step size", lambda: list(step_size(task, config, example_state)))
    large = operations > LARGE_STEP
    options = compiler_options(large)
    jit = functools.partial(jax.jit, compiler_options=options)
    measured = lambda name, measure: kept(f"traced bytes, {name}", measure)  # noqa: E731
    plan = run_plan(task, config, example_state, large, measured) if plan is None else plan  # one for every dynamics an epoch uses
    # Fixed order, no shuffling: minibatch i is always the same states.
    batches = jax.jit(lambda states: jax.tree.map(  # one program, not one eager reshape per leaf
        lambda a: a.reshape((config.train_size // config.batch, config.batch) + a.shape[1:]), states))(train_states)

    def init(seed):
        params = task.init_params(jax.random.PRNGKey(seed), config.zero_output)
        return TrainState(params, optimizer.init(params))

    def evaluate(params, initial_states, dynamics=task.dynamics):
        if task.evaluation is not None:
            return task.evaluation(params, initial_states).mean()
        return reference_loss(dynamics, params, initial_states, plan=plan)

    def update(dynamics, state, batch):
        loss, grads = flow_gradients(dynamics, flows, state.params, batch, plan)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        if "M" in flows and "R" in flows:
            row = lambda f: jax.tree.map(lambda a: a[flows.index(f)], grads)
            cosine = tree_cosine(row("M"), row("R"))
        else:
            cosine = jnp.nan
        # Every flow's gradient, not only the update: mode C's sign agreement
        # turns a NaN of g_R into a finite zero update.
        flows_finite = jnp.stack([_all_finite(jax.tree.map(lambda a, i=i: a[i], grads)) for i in range(len(flows))])
        return TrainState(params, opt_state), (loss, optax.tree.norm(updates), cosine, flows_finite)

    def evaluate_both(params, train_states, test_states, dynamics=task.dynamics):
        # Training and test states in one rollout: the program holds one copy of the simulator, not two.
        both = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), train_states, test_states)
        if task.evaluation is not None:
            return task.evaluation(params, both)
        return reference_losses(dynamics, params, both, plan=plan)

    def epoch_metrics(state, per_update, losses_of_both):
        """The epoch's metrics from its updates' outputs ([updates] each) and every state's loss."""
        losses, update_norms, cosines, flows_finite = per_update
        train_loss, test_loss = losses_of_both[:config.train_size].mean(), losses_of_both[config.train_size:].mean()
        # The optimizer state too: an overflowed Adam moment (v = inf) silently zeroes every later update.
        checks = [jnp.isfinite(losses).all(), jnp.isfinite(update_norms).all() & _all_finite(state),
                  jnp.isfinite(train_loss), jnp.isfinite(test_loss)] + list(flows_finite.all(axis=0))
        failed = sum(jnp.where(ok, 0, 1 << bit) for bit, ok in enumerate(checks))
        return {
            "batch_loss": losses.mean(),
            "train_loss": train_loss,
            "test_loss": test_loss,
            "update_norm": update_norms.mean(),
            "cosine": cosines.mean(),
            "finite": failed == 0,
            "nonfinite": failed,  # bit set per failed check, in the order of nonfinite_names(flows)
        }

    def epoch(state, batches, train_states, test_states, dynamics=task.dynamics):
        state, per_update = jax.lax.scan(lambda s, b: update(dynamics, s, b), state, batches)
        return state, epoch_metrics(state, per_update, evaluate_both(state.params, train_states, test_states, dynamics))

    def grid_epoch(state, value, batches, train_states, test_states):
        dynamics = task.dynamics if value is None else task.cell_option.dynamics(value)
        return epoch(state, batches, train_states, test_states, dynamics)

    def over_seeds(function, mapped=1):
        """Map ``function(*per_seed, *shared)`` over the leading seed axis of its first ``mapped`` arguments."""
        if config.seed_batching == "vmap":
            return lambda *args: jax.vmap(lambda *per_seed: function(*per_seed, *args[mapped:]))(*args[:mapped])
        # lax.map compiles the single-seed program once and loops it, so each
        # seed's numbers are bit-identical to that seed trained alone; XLA fuses
        # batched physics differently, which moves the last bits under vmap.
        return lambda *args: jax.lax.map(lambda per_seed: function(*per_seed, *args[mapped:]), args[:mapped])

    if grid:
        epoch_program = jit(over_seeds(grid_epoch, mapped=2))
    elif config.epoch_program == "whole" or config.epoch_program == "auto" and not (
            large or solves and _compile_side_by_side()):
        epoch_program = jit(over_seeds(epoch))
    else:
        epoch_program = PerUpdateEpoch(jit(over_seeds(functools.partial(update, task.dynamics))),
                                       jit(over_seeds(evaluate_both)), jit(over_seeds(epoch_metrics, mapped=3)))
    return Trainer(
        flows=flows,
        init=jit(over_seeds(init)),
        epoch=epoch_program,
        evaluate=jit(over_seeds(evaluate)),
        train_states=train_states,
        test_states=test_states,
        batches=batches,
        plan=plan,
        compiler_options=options,
    )


class PerUpdateEpoch:
    """An epoch as a Python loop over separately compiled programs: one update, one evaluation, its metrics.

    Called like the one-program epoch, ``(states, batches, train, test) -> (states,
    metrics)``, with the same metrics; ``lower(...).compile()`` compiles every
    program ahead, as ``jax.jit``'s does for the whole epoch. XLA compiles the
    pieces apart in a fraction of the time and memory it needs for one program
    holding them all; on a CPU of several cores the update and the evaluation
    compile side by side.
    """

    def __init__(self, update: Callable, evaluate: Callable, epoch_metrics: Callable):
        self.update, self.evaluate, self.epoch_metrics = update, evaluate, epoch_metrics

    def __call__(self, state, batches, train_states, test_states):
        outputs = []
        for index in range(_updates(batches)):
            state, output = self.update(state, jax.tree.map(lambda a, i=index: a[i], batches))
            outputs.append(output)
        per_update = jax.tree.map(lambda *each: jnp.stack(each, axis=1), *outputs)  # [seeds, updates]
        return state, self.epoch_metrics(state, per_update, self.evaluate(state.params, train_states, test_states))

    def lower(self, state, batches, train_states, test_states, lower_one: Callable | None = None):
        """The epoch for these arguments; its ``compile()`` lowers and compiles the pieces, each by
        ``lower_one(program, arguments, name)`` (default: the program's own ``lower``)."""
        return _LoweredPerUpdateEpoch(self, (state, batches, train_states, test_states),
                                      lower_one or (lambda program, arguments, name: program.lower(*arguments)))

    def compile_pieces(self, arguments: tuple, lower_one: Callable) -> PerUpdateEpoch:
        """The three programs compiled for the epoch's ``arguments``, each lowered by ``lower_one(program,
        arguments, name)``; each compiled program knows its outputs' shapes: nothing is traced twice."""
        state, batches, train_states, test_states = arguments
        update = lower_one(self.update, (state, jax.tree.map(lambda a: a[0], batches)), "update")
        evaluate = lower_one(self.evaluate, (state.params, train_states, test_states), "evaluate")
        if _compile_side_by_side():
            with concurrent.futures.ThreadPoolExecutor(1) as beside:
                evaluate = beside.submit(evaluate.compile)
                update = update.compile()
                evaluate = evaluate.result()
        else:
            update, evaluate = update.compile(), evaluate.compile()
        per_update = jax.tree.map(lambda a: jax.ShapeDtypeStruct((a.shape[0], _updates(batches)) + a.shape[1:], a.dtype),
                                  update.out_info[1])
        losses = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), evaluate.out_info)
        metrics = lower_one(self.epoch_metrics, (state, per_update, losses), "epoch_metrics").compile()
        return PerUpdateEpoch(update, evaluate, metrics)


class _LoweredPerUpdateEpoch(NamedTuple):
    epoch: PerUpdateEpoch
    arguments: tuple
    lower_one: Callable

    def compile(self) -> PerUpdateEpoch:
        return self.epoch.compile_pieces(self.arguments, self.lower_one)


def _compile_side_by_side() -> bool:
    """Whether two programs compile at once: XLA lets go of Python while it compiles, so a CPU of
    several cores compiles the evaluation beside the update. Not on one core (two compiles' memory
    for nothing), nor on a GPU, whose kernel autotuning would time candidates against each other."""
    return jax.default_backend() == "cpu" and usable_cores() > 1


def _updates(batches: PyTree) -> int:
    return len(jax.tree.leaves(batches)[0])


def _example_control(task: Task, config: TrainConfig, initial_state: PyTree) -> PyTree:
    params = parameter_shapes(task, config.zero_output)
    control = jax.eval_shape(task.dynamics.policy, params, initial_state)
    return jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), control)


def _operations(jaxpr) -> int:
    return sum(1 + sum(_operations(inner) for inner in jax.extend.core.jaxprs_in_params(equation.params))
               for equation in jaxpr.eqns)


def gpu_options() -> dict:
    """XLA options of the programs that hold a simulator step, compiled for a GPU.

    While it compiles for a GPU, XLA times candidate kernels of its matrix products and fusions
    ("autotuning") and by default (level 4) also fills their buffers and checks every candidate
    against a reference. Level 1 times them and checks none; level 0 does not time them at all. And
    XLA compiles a program's kernels on one thread unless told how many to use. On one H100, the
    cart-pole grid's four programs (240 cells each) compiled in 53-155 s with the defaults, in
    9-19 s with level 0 on every core but then trained twice as long, and in 11-22 s with level 1
    on every core, training as fast as with the defaults
    (experiments/startup_gpu/grid_compile.sh; results/startup/gpu-side-by-side/grid/).
    """
    return {"xla_gpu_autotune_level": 1, "xla_gpu_force_compilation_parallelism": usable_cores()}


def sample_states(task: Task, key: jax.Array, count: int) -> PyTree:
    """``count`` initial states of ``task`` from ``key``, as every run draws them.

    On a GPU by a program compiled with the GPU's options (an environment's reset is a large one);
    on a CPU eagerly: fused by jit, the states of cartpole_3 and quantum would differ in their last
    bits from the ones CPU runs have trained from.
    """
    if jax.default_backend() != "gpu":
        return task.sample_initial_states(key, count)
    return jax.jit(task.sample_initial_states, static_argnums=1, compiler_options=compiler_options())(key, count)


def compiler_options(large: bool = False) -> dict | None:
    """XLA options of a program that holds a simulator step; ``large``: ``large_step``'s answer.

    An option the user set in ``XLA_FLAGS`` (``--xla_gpu_autotune_level=4``: XLA's own checks) is
    left to it.
    """
    backend = jax.default_backend()
    options = dict(LARGE_STEP_CPU_OPTIONS) if large and backend == "cpu" else {}
    if backend == "gpu":
        options.update(unless_in_xla_flags(gpu_options()))
    return options or None


def unless_in_xla_flags(options: dict) -> dict:
    """``options`` less those the user set in ``XLA_FLAGS``, whose value holds."""
    flags = os.environ.get("XLA_FLAGS", "")
    return {name: value for name, value in options.items() if f"--{name}=" not in flags}


def large_step(task: Task, config: TrainConfig, initial_state: PyTree) -> bool:
    """Whether one simulator step has more than ``LARGE_STEP`` operations (``step_size``)."""
    return step_size(task, config, initial_state).operations > LARGE_STEP


class StepSize(NamedTuple):
    """What one traced simulator step holds."""

    operations: int  # inner loops' bodies counted once
    solves: bool  # a loop of data-dependent length: a constraint solver's iterations


def step_size(task: Task, config: TrainConfig, initial_state: PyTree) -> StepSize:
    """One trace of one simulator step, measured (``StepSize``)."""
    control = _example_control(task, config, initial_state)
    jaxpr = jax.make_jaxpr(task.dynamics.step)(initial_state, control).jaxpr
    return StepSize(_operations(jaxpr), _holds_while(jaxpr))


def _holds_while(jaxpr) -> bool:
    return any(equation.primitive.name == "while" or any(_holds_while(inner) for inner in
                                                          jax.extend.core.jaxprs_in_params(equation.params))
               for equation in jaxpr.eqns)


def memory_plan(task: Task, config: TrainConfig, initial_state: PyTree, plan: Plan | None = None,
                measured: Callable = measure_now) -> MemoryPlan:
    """The settings that fit ``task``'s gradient path (the derivative of ``plan``, default the task's own),
    at ``config.batch`` examples per update, into memory."""
    dynamics, plan = task.dynamics, task.plan if plan is None else plan
    control = _example_control(task, config, initial_state)
    size = lambda tree: sum(leaf.size for leaf in jax.tree.leaves(tree))
    known = 0 if plan.known_columns is None else len(plan.known_columns.indices)
    return plan_memory(dynamics.step, initial_state, control, dynamics.horizon, config.batch, plan.step_derivative,
                       tangents=size(initial_state) + size(control) - known, measured=measured)


def run_plan(task: Task, config: TrainConfig, initial_state: PyTree, large: bool, measured: Callable = measure_now) -> Plan:
    """How a run differentiates ``task``: the task's own plan, completed by the memory plan (Jacobian
    chunks or recomputed steps), a large step's single Jacobian pass (the task may ask for it too)
    and ``config.unroll``."""
    memory = memory_plan(task, config, initial_state, measured=measured)
    return dataclasses.replace(task.plan, unroll=config.unroll, jacobian_chunk=memory.jacobian_chunk,
                               rematerialize=memory.rematerialize,
                               jacobian_per_input=task.plan.jacobian_per_input and not large)


def _all_finite(tree: PyTree) -> jax.Array:
    leaves = [leaf for leaf in jax.tree.leaves(tree) if jnp.issubdtype(leaf.dtype, jnp.inexact)]
    return jnp.all(jnp.array([jnp.isfinite(leaf).all() for leaf in leaves])) if leaves else jnp.array(True)


def nonfinite_names(flows: tuple[str, ...], failed: int) -> list[str]:
    """What the ``nonfinite`` metric of an epoch says was not finite, in words."""
    names = ["batch loss", "update or optimizer state", "train loss", "test loss"] + [f"gradient of flow {f}" for f in flows]
    return [name for bit, name in enumerate(names) if int(failed) >> bit & 1]


def seed_array(config: TrainConfig) -> jax.Array:
    return jnp.arange(config.seed, config.seed + config.seeds, dtype=jnp.uint32)
