"""One run spread over several devices (``TrainConfig.devices``): the states an update rolls split
evenly across them, everything else (parameters, optimizer and critic states) held whole on each.

Every program of a spread trainer takes and returns its arguments whole on every device of the
mesh; inside, the rolled states (and an evaluation's starts, where they divide evenly) are
constrained to the mesh's one axis, and XLA's partitioner (GSPMD) splits the simulation, its
derivative and the resets by env. What merges the envs with the window's steps into one axis (the
critic's fit, the policy's batched pullback) it gathers whole on each device. Between programs
nothing is split, so checkpoints, divergence checks and evaluations see the same arrays as on one
device.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from stablebptt.errors import InputError, config_field

AXIS = "envs"


class Spread(NamedTuple):
    """The devices one run spans (``spread_of``)."""

    mesh: Mesh

    @property
    def count(self) -> int:
        return self.mesh.size

    @property
    def whole(self) -> NamedSharding:
        """Every array whole on every device."""
        return NamedSharding(self.mesh, PartitionSpec())

    def jit_options(self) -> dict:
        """``jax.jit``'s options that make a program take and give its arguments whole on every device."""
        return {"in_shardings": self.whole, "out_shardings": self.whole}

    def placed(self, tree: Any) -> Any:
        """``tree`` whole on every device: a program's arguments that stay the same from call to call
        move once, not at every call."""
        return jax.device_put(tree, self.whole)


def spread_of(config: Any) -> Spread | None:
    """The devices ``config.devices`` asks for (0: every device JAX sees), or None for one.

    Raises:
      InputError: more devices than JAX sees, or ``config.batch`` (the states each update rolls) not a
        multiple of their number.
    """
    visible = jax.devices()
    count = device_count(config)
    if count > len(visible):
        raise InputError(f"{config_field(config, 'devices')} {config.devices}: JAX sees {len(visible)} "
                         f"{visible[0].platform} device{'s' if len(visible) > 1 else ''} here: ask for at most "
                         f"{len(visible)} (a resumed run too)")
    if count == 1:
        return None
    if not splits_evenly(config.batch, count):
        raise InputError(f"{config_field(config, 'devices')}: {config_field(config, 'batch')} ({config.batch}) "
                         f"must split evenly over the {count} devices: make it a multiple of {count}")
    return Spread(Mesh(np.array(visible[:count]), (AXIS,)))


def splits_evenly(batch: int, devices: int) -> bool:
    """Whether ``batch`` states per update split evenly over ``devices`` (what ``spread_of`` asks of a run)."""
    return batch % devices == 0


def device_count(config: Any) -> int:
    """How many devices ``config.devices`` asks for (0: every device JAX sees)."""
    return len(jax.devices()) if config.devices == 0 else config.devices


def split(spread: Spread | None, tree: Any) -> Any:
    """``tree``'s arrays, each with the envs on its leading axis, split by env over the spread's
    devices inside a program (as they stand on one device: unchanged)."""
    if spread is None:
        return tree
    return jax.lax.with_sharding_constraint(tree, NamedSharding(spread.mesh, PartitionSpec(AXIS)))


def split_where_even(spread: Spread | None, tree: Any) -> Any:
    """``split``, where the leading axis divides evenly over the devices; else ``tree`` as it stands."""
    if spread is None or jax.tree.leaves(tree)[0].shape[0] % spread.count:
        return tree
    return split(spread, tree)
