"""An epoch compiled per update: for large steps, where one program of the whole epoch would take XLA long."""
from __future__ import annotations

import concurrent.futures
from typing import Callable, NamedTuple

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np

from stablebptt.flows.dynamics import PyTree
from stablebptt.timing import usable_cores


class PerUpdateEpoch:
    """An epoch as a Python loop over separately compiled programs: one update, one evaluation, its metrics.

    Called like the one-program epoch, ``(states, batches, train, test) -> (states,
    metrics)``, with the same metrics; ``lower(...).compile()`` compiles every
    program ahead, as ``jax.jit``'s does for the whole epoch. XLA compiles the
    pieces apart in a fraction of the time and memory it needs for one program
    holding them all; on a CPU of several cores the update and the evaluation
    compile side by side.
    """

    def __init__(self, update: Callable, evaluate: Callable | None, epoch_metrics: Callable, numbered: bool = False):
        # evaluate None: the epoch runs its updates alone (the trainer evaluates apart, ``Trainer.evaluation``).
        # numbered: the batches are the updates' numbers (training on episodes), a negative one skipped.
        self.update, self.evaluate, self.epoch_metrics = update, evaluate, epoch_metrics
        self.numbered = numbered

    def __call__(self, state, batches, train_states, test_states):
        outputs, updates = [], _updates(batches)
        for index in range(int((np.asarray(batches) >= 0).sum()) if self.numbered else updates):
            state, output = self.update(state, jax.tree.map(lambda a, i=index: a[i], batches))
            outputs.append(output)
        # An epoch cut short (``episodes.cut_short``): the updates it skipped, as nothing ran (``UpdateOutput.taken``).
        outputs += [jax.tree.map(jnp.zeros_like, outputs[0])] * (updates - len(outputs))
        per_update = jax.tree.map(lambda *each: jnp.stack(each, axis=1), *outputs)  # [seeds, updates]
        if self.evaluate is None:
            return state, self.epoch_metrics(state, per_update)
        return state, self.epoch_metrics(state, per_update, self.evaluate(state.params, train_states, test_states))

    def lower(self, state, batches, train_states, test_states, lower_one: Callable | None = None,
              update_now: bool = False):
        """The epoch for these arguments; its ``compile()`` lowers and compiles the pieces, each by
        ``lower_one(program, arguments, name)`` (default: the program's own ``lower``). ``update_now``:
        the update is traced and lowered here, in the caller's thread, and its compile, begun in another,
        holds Python's lock no longer than XLA's own work; traced in that thread, the update shared the
        lock with whatever the caller traced meanwhile (a GPU's start: the reward check)."""
        arguments = (state, batches, train_states, test_states)
        lower_one = lower_one or (lambda program, arguments, name: program.lower(*arguments))
        return _LoweredPerUpdateEpoch(self, arguments, lower_one,
                                      self.lowered_update(arguments, lower_one) if update_now else None)

    def lowered_update(self, arguments: tuple, lower_one: Callable):
        """The update lowered for the epoch's ``arguments`` by ``lower_one(program, arguments, name)``."""
        state, batches = arguments[:2]
        return lower_one(self.update, (state, jax.tree.map(lambda a: a[0], batches)), "update")

    def compile_pieces(self, arguments: tuple, lower_one: Callable, update=None) -> PerUpdateEpoch:
        """The three programs compiled for the epoch's ``arguments``, each lowered by ``lower_one(program,
        arguments, name)`` (the update's may be given, lowered already); each compiled program knows its
        outputs' shapes: nothing is traced twice."""
        state, batches, train_states, test_states = arguments
        update = self.lowered_update(arguments, lower_one) if update is None else update
        if self.evaluate is None:
            update = update.compile()
            metrics = lower_one(self.epoch_metrics, (state, _stacked(update.out_info[1], batches)), "epoch_metrics")
            return PerUpdateEpoch(update, None, metrics.compile(), self.numbered)
        evaluate = lower_one(self.evaluate, (state.params, train_states, test_states), "evaluate")
        if compile_side_by_side():
            with concurrent.futures.ThreadPoolExecutor(1) as beside:
                evaluate = beside.submit(evaluate.compile)
                update = update.compile()
                evaluate = evaluate.result()
        else:
            update, evaluate = update.compile(), evaluate.compile()
        per_update = _stacked(update.out_info[1], batches)
        losses = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), evaluate.out_info)
        metrics = lower_one(self.epoch_metrics, (state, per_update, losses), "epoch_metrics").compile()
        return PerUpdateEpoch(update, evaluate, metrics, self.numbered)


class _LoweredPerUpdateEpoch(NamedTuple):
    epoch: PerUpdateEpoch
    arguments: tuple
    lower_one: Callable
    update: object = None  # the update lowered already (``lower``'s ``update_now``), else lowered as it compiles

    def compile(self) -> PerUpdateEpoch:
        return self.epoch.compile_pieces(self.arguments, self.lower_one, self.update)


def compile_side_by_side() -> bool:
    """Whether two programs compile at once: XLA lets go of Python while it compiles, so a CPU of
    several cores compiles the evaluation beside the update. Not on one core (two compiles' memory
    for nothing), nor on a GPU, whose kernel autotuning would time candidates against each other."""
    return jax.default_backend() == "cpu" and usable_cores() > 1


def _stacked(output_info: PyTree, batches: PyTree) -> PyTree:
    """The shapes of an epoch's update outputs stacked [seeds, updates, ...] from one update's."""
    return jax.tree.map(lambda a: jax.ShapeDtypeStruct((a.shape[0], _updates(batches)) + a.shape[1:], a.dtype),
                        output_info)


def _updates(batches: PyTree) -> int:
    return len(jax.tree.leaves(batches)[0])
