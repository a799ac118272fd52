"""How a task's programs compile: XLA's options per backend, the size of a traced step, the memory plan."""
from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import os
import threading
import time
from typing import Any, Callable, NamedTuple

import jax
import jax.extend
import jax.numpy as jnp

from stablebptt.engine.checks import parameter_shapes
from stablebptt.engine.config import LARGE_STEP, TrainConfig, batched_seeds
from stablebptt.engine.memory import MemoryPlan, budget_bytes, gigabytes, measure_now, plan_memory
from stablebptt.engine.spread import device_count
from stablebptt.engine.task import Task
from stablebptt.errors import InputError, config_field
from stablebptt.flows.dynamics import Plan, PyTree
from stablebptt.timing import usable_cores

# XLA:CPU's default fusion emitters compute each element of a fusion by calling the
# functions of its operands, so an operand that many elements read is recomputed for each.
# MJX's kinematics of a deep tree fuse into long elementwise chains: humanoid_CMU's first
# 5-step epoch had not ended after 20 minutes, nearly all of it in one fusion of 623
# operations that yields 24 numbers; with XLA's loop emitter it takes 5-7 s. Small steps
# keep the fusion emitters: their updates run 15-30% faster with them.
LARGE_STEP_CPU_OPTIONS = {"xla_cpu_use_fusion_emitters": False}


def _example_control(task: Task, params: PyTree, initial_state: PyTree) -> PyTree:
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
    (the records: ``git ls-tree fb065bd results/startup/gpu-side-by-side/grid/``).
    """
    return {"xla_gpu_autotune_level": 1, "xla_gpu_force_compilation_parallelism": usable_cores()}


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


def untimed_options() -> dict:
    """XLA options of a program compiled beside another (``beside``) or run once: on a GPU none
    of its kernels is timed (autotuning level 0), so that a compile timing its own kernels meanwhile
    chooses them undisturbed."""
    return unless_in_xla_flags({"xla_gpu_autotune_level": 0}) if jax.default_backend() == "gpu" else {}


def host_cpu() -> jax.Device | None:
    """The CPU of the host whose accelerator the programs compile for; None on a CPU alone, or where
    JAX_PLATFORMS leaves the CPU out."""
    if jax.default_backend() == "cpu":
        return None
    try:
        return jax.devices("cpu")[0]
    except RuntimeError:  # JAX_PLATFORMS without the CPU
        return None


def beside(function: Callable[[], Any], name: str) -> concurrent.futures.Future:
    """``function()`` run in a thread of its own, its result (or its error) in the future returned. XLA
    lets go of Python while it compiles: a compile begun here goes on while the caller traces or
    compiles another program. The thread runs under the caller's JAX settings (float64, matmul precision),
    which JAX keeps per thread."""
    result: concurrent.futures.Future = concurrent.futures.Future()
    x64, precision = jax.config.jax_enable_x64, jax.config.jax_default_matmul_precision

    def run():
        try:
            with jax.enable_x64(x64), jax.default_matmul_precision(precision):
                result.set_result(function())
        except BaseException as error:  # noqa: BLE001 - handed to whoever waits for the result
            result.set_exception(error)

    # No daemon: a process that ends early (a refusal) waits for it to finish, since XLA cannot be
    # stopped mid-compile and a daemon thread inside it aborts the interpreter's exit.
    threading.Thread(target=run, name=name).start()
    return result


class CompiledBeside:
    """A lowered program compiling in a thread of its own (``beside``), for arguments shaped as
    ``shapes``; called, it waits for its compile and runs."""

    def __init__(self, lowered: Any, shapes: Any, name: str, options: dict | None = None):
        self.shapes = shapes
        self.future = beside(lambda: lowered.compile(options or None), name)

    def wait(self) -> float:
        """Waits for the compile (its error raised here): the seconds waited."""
        started = time.perf_counter()
        self.future.result()
        return time.perf_counter() - started

    def __call__(self, *arguments):
        return self.future.result()(*arguments)


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
    solves: bool  # a loop of data-dependent length: a constraint solver's iterations (not where
    # physics.constraint_derivatives.BOUNDED_SOLVER_ITERATIONS gives them a known length)


def step_size(task: Task, config: TrainConfig, initial_state: PyTree) -> StepSize:
    """One trace of one simulator step, measured (``StepSize``)."""
    control = _example_control(task, parameter_shapes(task, config.zero_output), initial_state)
    jaxpr = jax.make_jaxpr(task.dynamics.step)(initial_state, control).jaxpr
    return StepSize(_operations(jaxpr), holds_while(jaxpr))


def holds_while(jaxpr) -> bool:
    """Whether a program holds a loop whose length is known only as it runs, in its inner programs too."""
    return any(equation.primitive.name == "while" or any(holds_while(inner) for inner in
                                                          jax.extend.core.jaxprs_in_params(equation.params))
               for equation in jaxpr.eqns)


def memory_plan(task: Task, config: TrainConfig, initial_state: PyTree, plan: Plan | None = None,
                measured: Callable = measure_now) -> MemoryPlan:
    """The settings that fit ``task``'s gradient path (the derivative of ``plan``, default the task's own),
    at ``config.batch`` examples per update and seed, every seed batched in one program (vmap) beside
    the others, into one device's memory: the examples split evenly over ``config.devices``."""
    dynamics, plan = task.dynamics, task.plan if plan is None else plan
    params = parameter_shapes(task, config.zero_output)
    budget, networks = budget_bytes(), networks_bytes(params, config)
    if networks >= budget:  # the gradient path's budget is what the networks leave
        field = functools.partial(config_field, config)
        critic = (f" or the critic ({field('critic_width')}, {field('critic_depth')}, {field('critics')})"
                  if config.critic else "")
        raise InputError(f"the networks' parameters need {gigabytes(networks)} with their gradients and Adam's moments"
                         f"{f' over {config.seeds} seeds' if config.seeds > 1 else ''}, more than the {gigabytes(budget)} "
                         f"this machine can give them: make the policy smaller (its hidden layers' widths and count)"
                         f"{critic}, or train fewer {field('seeds')}")
    control = _example_control(task, params, initial_state)
    size = lambda tree: sum(leaf.size for leaf in jax.tree.leaves(tree))
    known = 0 if plan.known_columns is None else len(plan.known_columns.indices)
    return plan_memory(dynamics.step, initial_state, control, dynamics.horizon, config.batch, plan.step_derivative,
                       tangents=size(initial_state) + size(control) - known, budget=budget - networks, measured=measured,
                       copies=batched_seeds(config),  # seeds batched hold their paths at once
                       devices=device_count(config))


def networks_bytes(params: PyTree, config: TrainConfig) -> int:
    """What the networks hold beside the gradient path, in bytes, over every seed (the training state holds each
    seed's, batched or not): the policy's parameters ``params`` (their shapes) and, training with the critic, its
    weights past its first layer (a lower bound of its parameters), each with a gradient and Adam's two moments."""
    policy = sum(leaf.size * leaf.dtype.itemsize for leaf in jax.tree.leaves(params))
    width, depth = config.critic_width, config.critic_depth
    critic = config.critics * ((depth - 1) * width ** 2 + width) * 4 if config.critic else 0  # float32 weights
    return 4 * (policy + critic) * config.seeds  # the parameters, their gradient and Adam's two moments


def run_plan(task: Task, config: TrainConfig, initial_state: PyTree, large: bool, measured: Callable = measure_now) -> Plan:
    """How a run differentiates ``task``: the task's own plan, completed by the memory plan (Jacobian
    chunks or recomputed steps), a large step's single Jacobian pass (the task may ask for it too)
    and ``config.unroll``."""
    longest = max(task.dynamics.horizon, task.episodes.length if task.episodes is not None else 0)
    if config.unroll > longest:  # 10^20 compiled 8.7 GB unrolling the evaluation's episodes whole
        raise InputError(f"{config_field(config, 'unroll')} {config.unroll}: a run's longest loop (a window, an "
                         f"episode) has {longest} steps")
    memory = memory_plan(task, config, initial_state, measured=measured)
    return dataclasses.replace(task.plan, unroll=config.unroll, jacobian_chunk=memory.jacobian_chunk,
                               rematerialize=memory.rematerialize,
                               jacobian_per_input=task.plan.jacobian_per_input and not large)
