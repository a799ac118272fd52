"""A run's training and test initial states: drawn by the task's sampler from the run's data keys
(``TrainConfig.data_seed``), on a GPU by a program of its own, and where they serve only the
evaluations (carried episodes) in a thread of their own while the rest of the set-up goes on."""
from __future__ import annotations

import concurrent.futures
from typing import NamedTuple

import jax

from stablebptt.engine.compiling import beside, compiler_options
from stablebptt.engine.config import TrainConfig, data_keys
from stablebptt.engine.task import Task
from stablebptt.flows.dynamics import PyTree


class InitialStates(NamedTuple):
    """A run's training and test initial states, drawn while the rest of its set-up goes on
    (``make_trainer``): their shapes at once, their values once drawn."""

    shapes: tuple[PyTree, PyTree]  # (train, test): jax.ShapeDtypeStruct trees, or the arrays themselves
    drawn: concurrent.futures.Future  # -> (train, test) arrays

    @classmethod
    def at_hand(cls, train: PyTree, test: PyTree) -> "InitialStates":
        """States drawn already: their shapes are the arrays (placed on a spread's devices, as lowering needs)."""
        drawn: concurrent.futures.Future = concurrent.futures.Future()
        drawn.set_result((train, test))
        return cls((train, test), drawn)


def drawn_counts(config: TrainConfig) -> tuple[int, int]:
    """How many training and test initial states a run draws (``draw_initial_states``): the counts the
    trainer's task check samples at, so that an environment's batched reset is traced for no other."""
    return config.train_size, config.test_size


def draw_initial_states(task: Task, config: TrainConfig, deferred: bool) -> InitialStates:
    """The run's training and test initial states (``TrainConfig.data_seed``), the test states' reset
    compiling while the training states' does (on a GPU, one program each). ``deferred``: drawn in a
    thread of their own, their shapes traced here (the values are the same either way)."""
    train_key, test_key = data_keys(config.data_seed)
    train_count, test_count = drawn_counts(config)

    def draw():
        testing = beside(lambda: sample_states(task, test_key, test_count), "stablebptt-test-states")
        return sample_states(task, train_key, train_count), testing.result()

    if not deferred:
        return InitialStates.at_hand(*draw())
    # check_task refuses a sampler that does not trace on shapes alone.
    shapes = tuple(jax.eval_shape(lambda key, count=count: task.sample_initial_states(key, count), key)
                   for key, count in ((train_key, train_count), (test_key, test_count)))
    return InitialStates(shapes, beside(draw, "stablebptt-initial-states"))


def sample_states(task: Task, key: jax.Array, count: int) -> PyTree:
    """``count`` initial states of ``task`` from ``key``, as every run draws them.

    On a GPU by a program compiled with the GPU's options (an environment's reset is a large one);
    on a CPU eagerly: fused by jit, the states of cartpole_3 and quantum would differ in their last
    bits from the ones CPU runs have trained from.
    """
    if jax.default_backend() != "gpu":
        return task.sample_initial_states(key, count)
    return jax.jit(task.sample_initial_states, static_argnums=1, compiler_options=compiler_options())(key, count)
