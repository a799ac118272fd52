"""What BPTT differentiates (``Dynamics``), how (``Plan``) and how its state's leaves are laid out.

A state is any pytree. Its float and complex leaves carry derivatives; the others (a step counter,
a contact index, a PRNG key) ride along a rollout untouched: ``split`` and ``join`` separate and
restore them. The flows put copies and time steps on leading axes; the helpers at the end shape
those batches.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, fields
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from stablebptt.errors import InputError, TaskError, config_field, keywords_named, refuse_keyword, whole_number

PyTree = Any


class KnownColumns(NamedTuple):
    """Columns of a step's state Jacobian known in advance, over the flattened state.

    Column ``columns[:, i]`` is d step(x, u) / d x[indices[i]] at every (x, u):
    a symmetry, such as a shift that passes straight through to the next state.
    Both arrays are static NumPy arrays.
    """

    indices: np.ndarray  # [known] entries of the flattened state
    columns: np.ndarray  # [state, known]


def check_known_columns(known: KnownColumns, state_size: int) -> None:
    """``InputError`` unless ``known`` gives whole columns of the step's state Jacobian: indices of the
    flattened state (one past it would take a control's column, changing the gradients without a word) and
    columns as long as the state."""
    indices, columns = np.asarray(known.indices), np.asarray(known.columns)
    within = np.all((indices >= 0) & (indices < state_size))
    if not (indices.ndim == 1 and np.issubdtype(indices.dtype, np.integer) and within
            and len(set(indices.tolist())) == indices.size and columns.shape == (state_size, indices.size)):
        raise InputError(f"Plan.known_columns must give distinct indices of the flattened state's {state_size} entries "
                         f"and columns of shape ({state_size}, indices), got indices {indices.tolist()} and columns "
                         f"of shape {columns.shape}")


STEP_DERIVATIVES = ("reverse", "forward")
POLICY_GRADIENTS = ("batched", "per-step")


@keywords_named
@dataclass(frozen=True, eq=False)
class Plan:
    """How the engine differentiates a ``Dynamics``: the same gradients, computed another way.

    ``make_trainer`` chooses one per run (``Trainer.plan``) from what the task
    knows (``Task.plan``), the memory the gradient path needs, the size of one
    step and ``TrainConfig.unroll``; a plan passed to it is taken whole instead
    (``dataclasses.replace(trainer.plan, ...)`` changes one choice and keeps
    the others).
    The engine's functions (``flow_gradients`` and the rest) take one too,
    ``Plan()`` where none is given.

    Attributes:
      step_derivative: how the reverse pass differentiates ``step``:
        ``"reverse"`` pulls cotangents back through it step by step (best for
        large states); ``"forward"`` builds every step's full Jacobian by
        forward mode, all steps in one batched pass after the rollout, and
        runs the reverse pass on them (``stablebptt.flows.linearized``). For small
        states simulated by many tiny operations (MJX) this replaces thousands
        of tiny sequential kernels by a few large ones.
      unroll: steps per iteration of the rollout loops (``lax.scan``'s
        ``unroll``). On a GPU, where each step is dozens of tiny kernels, 5-10
        cuts the kernels and copies per step; on a CPU 1 is fastest and
        compiles quickest.
      known_columns: optional, for ``"forward"``: columns of the step's state
        Jacobian that a symmetry fixes (``KnownColumns``), e.g. the position and
        velocity of a system nothing ties to the world (translation and Galilean
        boost). No tangent is pushed through the simulator for them.
      jacobian_chunk: for ``"forward"``: examples whose step Jacobians are
        computed at once (None: all T x batch); bounds the memory of large scenes
        (``stablebptt.engine.memory.plan_memory`` chooses it).
      rematerialize: for ``"reverse"``: store only each step's inputs and
        recompute the step in the backward pass, trading one more forward pass
        for the memory of every step's intermediates.
      jacobian_per_input: for ``"forward"``: one forward pass per input leaf
        (True: each skips the stages its input does not reach) or one pass for
        all (False: one copy of the differentiated step, far quicker to compile
        for large scenes, and for any scene whose every input reaches a costly
        stage such as a constraint solver); see ``step_jacobians``. Large
        steps always take one pass.
      policy_gradient: for ``"reverse"``: ``"batched"`` computes each flow's
        parameter gradient after the reverse pass, in one batched pullback over
        every visited state (few large matrix products; the flows that do not
        pass through the policy's input then skip it per step), at the price of
        one more policy forward pass over those states; ``"per-step"`` pulls
        every flow back through the policy at every step (cheaper where the
        policy's batched backward pass is slow: XLA's CPU convolutions).
      chunk_placement: for ``"forward"`` with ``jacobian_chunk``: applied to each chunk of examples
        inside the loop over chunks (a run spread over devices splits every chunk by device, which a
        loop over a split axis would undo); None: each chunk as it stands.
    """

    step_derivative: str = "reverse"
    unroll: int = 1
    known_columns: KnownColumns | None = None
    jacobian_chunk: int | None = None
    rematerialize: bool = False
    jacobian_per_input: bool = True
    policy_gradient: str = "batched"
    chunk_placement: Callable[[PyTree], PyTree] | None = None

    def __post_init__(self):
        for name, allowed in (("step_derivative", STEP_DERIVATIVES), ("policy_gradient", POLICY_GRADIENTS)):
            if getattr(self, name) not in allowed:
                raise InputError(f"Plan.{name} must be one of {', '.join(allowed)}, got {getattr(self, name)!r}")
        if not whole_number(self.unroll) or self.unroll < 1:
            raise InputError(f"Plan.unroll must be a positive whole number, got {self.unroll!r}")
        if self.jacobian_chunk is not None and (not whole_number(self.jacobian_chunk) or self.jacobian_chunk < 1):
            raise InputError(f"Plan.jacobian_chunk must be None or a positive whole number, got {self.jacobian_chunk!r}")
        for name in ("rematerialize", "jacobian_per_input"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise InputError(f"Plan.{name} must be True or False, got {getattr(self, name)!r}")
        if self.known_columns is not None and not isinstance(self.known_columns, KnownColumns):
            raise InputError(f"Plan.known_columns must be None or a KnownColumns, got {type(self.known_columns).__name__}")
        if self.chunk_placement is not None and not callable(self.chunk_placement):
            raise InputError(f"Plan.chunk_placement must be None or a function, got {type(self.chunk_placement).__name__}")


@dataclass(frozen=True, init=False)
class Dynamics:
    """What BPTT differentiates: a policy, a simulator step and a trajectory loss.

    How the engine differentiates it is a ``Plan``, apart.

    Attributes:
      step: ``step(state, control) -> state``; a pytree of float arrays.
      policy: ``policy(params, state) -> control``; observation included.
      loss: ``loss(states, controls) -> scalar`` for ONE trajectory, where
        ``states`` stacks x_1..x_T and ``controls`` stacks u_0..u_{T-1}.
      horizon: number of steps T.
    """

    step: Callable[[PyTree, PyTree], PyTree]
    policy: Callable[[PyTree, PyTree], PyTree]
    loss: Callable[[PyTree, PyTree], jax.Array]
    horizon: int

    def __init__(self, step: Callable, policy: Callable, loss: Callable, horizon: int, **settings):
        # The engine settings Dynamics once carried: named, so a caller learns where they went.
        own = [item.name for item in fields(self)]
        plan_settings = {item.name for item in fields(Plan)}
        unknown = [name for name in settings if name not in plan_settings]
        if unknown:  # the first in the caller's order, as keywords_named names one
            named = functools.partial(config_field, type(self))
            refuse_keyword(unknown[0], own, named, f"no field {named(unknown[0])}")
        if settings:
            raise InputError(f"Dynamics takes {', '.join(own[:-1])} and {own[-1]} only: {', '.join(sorted(settings))} "
                             f"belong{'s' if len(settings) == 1 else ''} to stablebptt.Plan; pass a Plan as "
                             "make_trainer's or flow_gradients' plan argument")
        for name, value in zip(own, (step, policy, loss, horizon)):
            object.__setattr__(self, name, value)


def check_dynamics(dynamics: Any) -> None:
    """The fields of a ``Dynamics`` that need no tracing: the horizon, and functions where functions belong."""
    if not isinstance(dynamics, Dynamics):
        raise TaskError(f"expected a stablebptt.Dynamics, got {type(dynamics).__name__}")
    if not whole_number(dynamics.horizon) or dynamics.horizon < 1:
        raise TaskError(f"Dynamics.horizon must be a positive whole number of steps, got {dynamics.horizon!r}")
    for name in ("step", "policy", "loss"):
        if not callable(getattr(dynamics, name)):
            raise TaskError(f"Dynamics.{name} must be a function, got {getattr(dynamics, name)!r}")


def differentiable(leaf) -> bool:
    """Whether a state leaf carries a derivative: float and complex arrays do; integers, booleans and
    PRNG keys (a step counter, a contact index, an environment's key) pass through a rollout untouched."""
    return jnp.issubdtype(jnp.result_type(leaf), jnp.inexact)


class Parts(NamedTuple):
    """A state split into its differentiable leaves and the rest, to be put back by ``join``."""

    floats: list
    others: list
    treedef: Any
    is_float: tuple[bool, ...]


def split(tree: PyTree) -> Parts:
    leaves, treedef = jax.tree.flatten(tree)
    is_float = tuple(differentiable(leaf) for leaf in leaves)
    return Parts([a for a, f in zip(leaves, is_float) if f], [a for a, f in zip(leaves, is_float) if not f],
                 treedef, is_float)


def join(parts: Parts, floats: list | None = None, others: list | None = None) -> PyTree:
    """The state of ``parts`` with its float leaves (or its other leaves) replaced where given."""
    floats, others = iter(parts.floats if floats is None else floats), iter(parts.others if others is None else others)
    return jax.tree.unflatten(parts.treedef, [next(floats) if f else next(others) for f in parts.is_float])



def split_cotangent(cotangent: PyTree) -> Parts:
    """A cotangent split as ``split`` splits its primal: float0 leaves belong to leaves without a derivative."""
    leaves, treedef = jax.tree.flatten(cotangent)
    is_float = tuple(leaf.dtype != jax.dtypes.float0 for leaf in leaves)
    return Parts([a for a, f in zip(leaves, is_float) if f], [a for a, f in zip(leaves, is_float) if not f],
                 treedef, is_float)


def ravel_examples(tree: PyTree, leading_axes: int) -> jax.Array:
    """Each example of ``tree`` (after ``leading_axes`` batch axes) as one flat vector."""
    ravel = lambda example: ravel_pytree(example)[0]
    for _ in range(leading_axes):
        ravel = jax.vmap(ravel)
    return ravel(tree)



def stack_copies(tree: PyTree, copies: int) -> PyTree:
    return jax.tree.map(lambda a: jnp.broadcast_to(a, (copies,) + jnp.shape(a)), tree)


def first_copy(tree: PyTree) -> PyTree:
    return jax.tree.map(lambda a: a[0], tree)


def one_state_shape(states: PyTree) -> PyTree:
    """The shapes and dtypes of one state of the batch ``states`` (arrays or shapes, the batch their leading axis)."""
    return jax.tree.map(lambda leaf: jax.ShapeDtypeStruct(leaf.shape[1:], leaf.dtype), states)


def merge_axes(tree: PyTree, axes: int) -> PyTree:
    """Merge the first ``axes`` axes of every leaf into one."""
    return jax.tree.map(lambda a: a.reshape((math.prod(a.shape[:axes]),) + a.shape[axes:]), tree)

