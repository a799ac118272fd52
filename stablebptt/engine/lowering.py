"""A run's epoch traced and lowered before its values exist (``lowered_epoch``), from the shapes of the
state ``Trainer.init`` gives (``state_shapes``), with the programs that compile beside it."""
from __future__ import annotations

from typing import Any, NamedTuple

import jax

from stablebptt.engine.compiling import CompiledBeside, untimed_options
from stablebptt.engine.config import TrainConfig, seed_array
from stablebptt.engine.program_store import cache_dir, keep_also, lower_epoch, lower_kept
from stablebptt.engine.shapes import tracing_shapes
from stablebptt.engine.training import Trainer, TrainState


class LoweredEpoch(NamedTuple):
    """A trainer's epoch traced and lowered (``lowered_epoch``) for states shaped as ``shapes``."""

    lowered: Any  # its compile() gives the epoch's program
    shapes: Any  # the states' shapes (jax.ShapeDtypeStruct) it was lowered for
    compiled: Any = None  # that program, compiled already (``prepare``: beside a check still running)
    evaluation: CompiledBeside | None = None  # the trainer's evaluation, compiling beside the epoch's compile
    init_rest: CompiledBeside | None = None  # its init's part that waits for no check (``Initializer.rest``), too
    refill: CompiledBeside | None = None  # the program each epoch starts with (``Trainer.refill``), too


def state_shapes(trainer: Trainer, seeds: Any) -> Any:
    """The shapes of ``trainer.init(seeds)``, traced with no values: a task's check still running need
    not have answered (it decides the parameters' start, not their shapes), and a carried population's
    shapes come from one reset's (``tracing_shapes``)."""
    # Each part through a function of its own, not its jit: JAX would keep a jit's trace for the next
    # call, and this one's parameters start before the check has decided how, its population unreset.
    policy = getattr(trainer.init.policy, "__wrapped__", trainer.init.policy)
    rest = getattr(trainer.init.rest, "__wrapped__", trainer.init.rest)
    with tracing_shapes():
        params, opt_state, log_std = jax.eval_shape(lambda seeds: policy(seeds), seeds)
        carried_and_critic = jax.eval_shape(lambda seeds: rest(seeds), seeds)
    return TrainState(params, opt_state, *carried_and_critic, log_std)


def lowered_epoch(trainer: Trainer, config: TrainConfig, program_key: dict | None = None,
                  beside: bool = True, update_now: bool = False) -> LoweredEpoch:
    """``trainer``'s epoch traced and lowered for the states ``trainer.init`` gives, from their shapes
    alone: a task's check still running (``Task.settle``, which decides the parameters' start) need
    not have answered, and XLA compiles that check beside this trace. A ``PerUpdateEpoch`` (a large
    step; a constraint solver on a CPU of several cores) is traced as it compiles instead (its metrics'
    program shaped by the update's), its update here where ``update_now`` (an epoch compiled at once, in
    another thread). ``program_key`` as ``train_epochs``; ``beside``: ``programs_beside``."""
    shapes = state_shapes(trainer, seed_array(config))
    arguments = (shapes, trainer.batches, *trainer.initial_states.shapes)  # the states may still be drawn
    lowered = LoweredEpoch(lower_epoch(trainer.epoch, arguments, trainer.kept_under(program_key), cache_dir(),
                                       trainer.compiler_options, update_now), shapes)
    return programs_beside(lowered, trainer, config, program_key) if beside else lowered


def programs_beside(lowered: LoweredEpoch, trainer: Trainer, config: TrainConfig,
                    program_key: dict | None = None, init: bool = True) -> LoweredEpoch:
    """``lowered`` with the trainer's evaluation and its population's resets (each epoch's, and with
    ``init`` its first: a resume reads its population from the checkpoint) compiling beside, to be
    compiled beside the epoch; on a GPU with none of their kernels timed while the epoch's are. Each
    epoch's refill is kept under ``program_key`` as the epoch is (``program_store.lower_kept``)."""
    seeds, params = seed_array(config), lowered.shapes.params
    evaluation = None if trainer.evaluation is None else CompiledBeside(
        trainer.evaluation.lower(params, *trainer.initial_states.shapes), params,
        "stablebptt-evaluation", untimed_options())
    init_rest = None if trainer.episodes is None or not init else CompiledBeside(
        trainer.init.rest.lower(seeds), seeds, "stablebptt-init", untimed_options())
    refill = None if trainer.refill is None else CompiledBeside(
        lowered_refill(trainer, lowered.shapes, program_key), lowered.shapes, "stablebptt-refill", untimed_options())
    return lowered._replace(evaluation=evaluation, init_rest=init_rest, refill=refill)


def refill_kept_also(trainer: Trainer, states: Any, program_key: dict | None, other: dict | None) -> None:
    """The trainer's refill, kept under ``program_key`` (``lowered_refill``), kept under ``other`` too."""
    if trainer.refill is not None:
        keep_also(trainer.kept_under(program_key), trainer.kept_under(other), "refill", (states,))


def lowered_refill(trainer: Trainer, states: Any, program_key: dict | None = None) -> Any:
    """The trainer's refill (``Trainer.refill``) lowered for ``states`` (arrays, or their shapes), from its
    traced program kept under ``program_key`` as the epoch is (``program_store.lower_kept``)."""
    return lower_kept(trainer.refill, (states,), trainer.kept_under(program_key), "refill", trainer.compiler_options,
                      cache_dir())
