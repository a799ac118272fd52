"""The gradient flows by name, where each cuts the backward pass, and the modes that combine them.

``FLOWS`` and ``KEEPS`` define the flows (the table in ``stablebptt.flows.gradients``); ``MODE_TABLE`` is the
one list of training modes: the flows each needs and how its update combines their gradients;
``MODE_ORDER`` is the order figures and tables show them in.
Every consumer (training, plots, the benchmark, sweeps) iterates over these.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import jax
import jax.numpy as jnp
import optax

from stablebptt.errors import InputError
from stablebptt.flows.dynamics import PyTree

FLOWS = ("R", "M", "S")

# Which parts of the pulled-back state cotangent each flow keeps:
# (through the simulator, through the policy's input).
KEEPS = {"R": (True, True), "M": (True, False), "S": (False, False)}


@dataclass(frozen=True)
class Mode:
    """A training mode: the flows its update needs and how it combines their gradients.

    Attributes:
      name: the ``--mode`` value.
      flows: the flows it needs, in canonical order (``FLOWS``).
      combine: ``combine(gradients) -> update``, ``gradients`` a dict flow -> gradient pytree.
      description: a few words for help texts.
    """

    name: str
    flows: tuple[str, ...]
    combine: Callable[[dict[str, PyTree]], PyTree]
    description: str


def _only(flow: str) -> Callable[[dict[str, PyTree]], PyTree]:
    return lambda gradients: gradients[flow]


# Every mode, in the paper's order. A new combination of flows is one more row here.
MODE_TABLE: dict[str, Mode] = {mode.name: mode for mode in (
    Mode("R", ("R",), _only("R"), "regular BPTT"),
    Mode("M", ("M",), _only("M"), "the physics path"),
    Mode("S", ("S",), _only("S"), "one step"),
    Mode("C", ("R", "M"), lambda gradients: sign_agreement(gradients["M"], gradients["R"]),
         "combined: g_M where its sign agrees with g_R"),
)}
MODES = tuple(MODE_TABLE)
# The paper's figures' order (R, M, C, S), from the table: a mode after the last flow it needs, a combination after it.
MODE_ORDER = tuple(sorted(MODES, key=lambda m: (max(map(FLOWS.index, MODE_TABLE[m].flows)), len(MODE_TABLE[m].flows))))


def flows_needed(mode: str, with_cosine: bool = True) -> tuple[str, ...]:
    """The flows a mode's update needs, in canonical order (R, M, S).

    Any mode also computes M and R when the cosine of the two is logged, which
    is cheap because the forward pass is shared.
    """
    if mode not in MODE_TABLE:
        raise InputError(f"unknown mode {mode!r}: choose one of {', '.join(MODES)}")
    needed = set(MODE_TABLE[mode].flows)
    if with_cosine:
        needed |= {"M", "R"}
    return tuple(f for f in FLOWS if f in needed)


def sign_agreement(grad_m: PyTree, grad_r: PyTree) -> PyTree:
    """The combined update C: g_M where sign(g_M) == sign(g_R), else 0, element-wise."""
    return jax.tree.map(lambda m, r: jnp.where(jnp.sign(m) == jnp.sign(r), m, jnp.zeros_like(m)), grad_m, grad_r)


def tree_cosine(a: PyTree, b: PyTree) -> jax.Array:
    """Cosine similarity of two pytrees seen as flat vectors (0 if either is 0)."""
    dot = sum(jnp.vdot(x, y) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))
    norms = optax.tree.norm(a) * optax.tree.norm(b)
    return jnp.where(norms > 0, dot / jnp.where(norms > 0, norms, 1.0), 0.0)


def select_flow(mode: str, flows: tuple[str, ...]) -> optax.GradientTransformation:
    """An optax transform turning stacked flow gradients into the update of ``mode``.

    Its input is the output of ``flow_gradients`` (a leading flow axis); its
    output is a plain gradient pytree, so it heads an ordinary chain::

        optimizer = optax.chain(select_flow("C", ("R", "M")),
                                optax.clip(1.0), optax.adam(1e-3))
    """
    needed = flows_needed(mode, with_cosine=False)
    missing = [f for f in needed if f not in flows]
    if missing:
        raise InputError(f"mode {mode} needs flows {needed}, but only {flows} are computed")

    def update(updates, state, params=None):
        del params
        rows = {flow: jax.tree.map(lambda a, i=flows.index(flow): a[i], updates) for flow in needed}
        return MODE_TABLE[mode].combine(rows), state

    return optax.GradientTransformation(lambda params: optax.EmptyState(), update)
