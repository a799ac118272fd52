"""Epochs into a run folder: a ``Trainer`` trained to ``config.epochs``, checkpointed as it goes."""
from __future__ import annotations

import time
from pathlib import Path
from typing import Callable, NamedTuple

import jax
import numpy as np

from stablebptt.engine.config import TrainConfig
from stablebptt.engine.fitting import LoweredEpoch, fit, nonfinite_message, zeroed_notice
from stablebptt.engine.program_store import cache_dir, compile_epoch
from stablebptt.engine.training import Trainer, TrainState
from stablebptt.runs.run_folder import METRICS_FILE, PARAMS_FILE, save_checkpoint, save_params, write_metrics


class Outcome(NamedTuple):
    status: str  # "complete", "interrupted" or "diverged"
    epoch: int  # last epoch whose state is saved
    state: TrainState
    rows: np.ndarray
    message: str


def train_epochs(
    trainer: Trainer,
    config: TrainConfig,
    run_dir: Path,
    state: TrainState,
    start_epoch: int,
    rows: np.ndarray,
    seeds: np.ndarray,
    on_epoch: Callable[[int, dict], None] = lambda epoch, metrics: None,
    on_compiled: Callable[[float], None] = lambda seconds: None,
    should_stop: Callable[[], bool] = lambda: False,
    owner: str = "",
    program_key: dict | None = None,
    lowered: LoweredEpoch | None = None,
) -> Outcome:
    """Train one run's seeds to ``config.epochs`` from ``start_epoch``, checkpointing into ``run_dir``.

    Stops early when ``should_stop()`` (after saving; the command line sets it on a
    signal) or on a non-finite loss or update (keeping the last good checkpoint).
    ``on_compiled`` gets the seconds the epoch took to compile; ``on_epoch`` the
    epoch's metrics, with its wall time under ``"seconds"``. Runs in any thread. With ``program_key``
    (everything that decides the epoch's program: ``program_store``) and JAX's compile cache on, the
    traced epoch is kept there, and a run with the same key skips tracing it. ``lowered``: the epoch
    lowered already (``lowered_epoch``), used where ``state`` has its shapes; ``on_compiled`` then
    gets the seconds of XLA's compile alone (and of a ``PerUpdateEpoch``'s tracing).
    """
    arguments = (trainer.batches, trainer.train_states, trainer.test_states)
    # Leaves alone: a carried env state's tree holds NumPy arrays in its static fields, which == cannot compare.
    leaf_shapes = lambda tree: [_shape_of(leaf) for leaf in jax.tree.leaves(tree)]  # noqa: E731
    if lowered is not None and leaf_shapes(state) == leaf_shapes(lowered.shapes):
        started = time.perf_counter()
        epoch_fn = lowered.lowered.compile()
        compile_seconds = time.perf_counter() - started
    else:
        epoch_fn, compile_seconds = compile_epoch(trainer.epoch, (state, *arguments), program_key, cache_dir(),
                                                  trainer.compiler_options)  # before timing epochs
    on_compiled(compile_seconds)

    def run_epoch(state):
        new_state, metrics = epoch_fn(state, *arguments)
        return new_state, jax.device_get(metrics)

    def save(epoch, state, rows):
        save_checkpoint(run_dir, epoch, state, rows, owner)
        save_params(run_dir / PARAMS_FILE, state.params)
        write_metrics(run_dir / METRICS_FILE, rows)

    def diverged(metrics):
        problem = nonfinite_message(trainer.flows, metrics)
        bad = [int(s) for s, ok in zip(seeds, np.atleast_1d(metrics["finite"])) if not ok]
        return f"{problem} at epoch {{epoch}} (seed {', '.join(map(str, bad))})" if problem else ""

    status, epoch, state, rows, problem = fit(run_epoch, state, start_epoch, config.epochs, rows, seeds, save,
                                              config.checkpoint_every, should_stop, on_epoch, diverged,
                                              noticed=lambda metrics: zeroed_notice(trainer.flows, metrics, seeds))
    if status == "diverged":
        message = (f"{problem.format(epoch=epoch + 1)}; stopped, the last good checkpoint (epoch {epoch}) "
                   f"is kept in {run_dir}")
    elif status == "interrupted":
        message = f"interrupted after epoch {epoch}; continue with --resume {run_dir}"
    else:
        message = ""
    return Outcome(status, epoch, state, rows, message)


def _shape_of(leaf) -> tuple:
    # A checkpoint's NumPy arrays carry no weak type where init's may: such a state is lowered anew.
    return leaf.shape, leaf.dtype, bool(getattr(leaf, "weak_type", False))
