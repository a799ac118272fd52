"""The optimizer of a run: gradient processing as one optax chain (clip, then Adam), per cell in a grid."""
from __future__ import annotations

import jax
import jax.extend
import jax.numpy as jnp
import optax

from stablebptt.engine.config import CLIP_MODES, TrainConfig
from stablebptt.errors import InputError, config_field
from stablebptt.flows.modes import FLOWS, MODES, select_flow

# Clip modes as optax transforms of the threshold: single runs and grid cells clip with the same ones.
CLIPPERS = {"value": optax.clip, "norm": optax.clip_by_global_norm, "none": lambda threshold: optax.identity()}


def _switch(transforms: list[optax.GradientTransformation], index: jax.Array) -> optax.GradientTransformation:
    """The update of ``transforms[index]`` for an index known only at run time (stateless transforms)."""
    def update(updates, state, params=None):
        candidates = [transform.update(updates, optax.EmptyState(), params)[0] for transform in transforms]
        return jax.tree.map(lambda *c: jnp.select([index == i for i in range(len(c))], c), *candidates), state

    return optax.GradientTransformation(lambda params: optax.EmptyState(), update)


def adam(config: TrainConfig, learning_rate) -> optax.GradientTransformation:
    """Adam with the run's decays (``TrainConfig.adam_b1``, ``adam_b2``): the policy's and the critic's."""
    return optax.adam(learning_rate, b1=config.adam_b1, b2=config.adam_b2)


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
        decay = []
        if config.lr_decay != 1:  # only then: a constant rate keeps the optimizer state of earlier runs
            decay = [optax.scale_by_schedule(lambda count: config.lr_decay ** count)]
        return optax.chain(select_flow(config.mode, flows), CLIPPERS[config.clip](clip_threshold),
                           adam(config, learning_rate), *decay)

    def chain_per_cell(learning_rate, clip_threshold, mode_index, clip_index):
        return optax.chain(_switch([select_flow(mode, flows) for mode in MODES], mode_index),
                           _switch([CLIPPERS[name](clip_threshold) for name in CLIP_MODES], clip_index),
                           adam(config, learning_rate))

    if per_cell:
        if config.lr_decay != 1:
            raise InputError(f"{config_field(config, 'lr_decay')}: a sweep's cells keep a constant learning rate; "
                             "train a decaying one as a run of its own")
        return optax.inject_hyperparams(chain_per_cell)(
            learning_rate=config.lr, clip_threshold=config.clip_threshold,
            mode_index=MODES.index(config.mode), clip_index=CLIP_MODES.index(config.clip))
    return optax.inject_hyperparams(chain)(learning_rate=config.lr, clip_threshold=config.clip_threshold)


def make_grid_optimizer(config: TrainConfig) -> optax.GradientTransformation:
    """``make_optimizer`` for sweep cells: all flows computed, mode and clip mode per cell."""
    return make_optimizer(config, FLOWS, per_cell=True)
