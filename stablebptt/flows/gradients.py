"""Every flow's gradient from one forward rollout (``flow_gradients``), and the literal stop_gradient
transcription of the flows' table (``reference_rollout``) both derivative modes are tested against."""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from stablebptt.errors import InputError, TaskError, users_call
from stablebptt.flows.adjoint_step import multi_adjoint_step
from stablebptt.flows.dynamics import (Dynamics, Plan, PyTree, check_dynamics, first_copy, one_state_shape,
                                       ravel_examples, stack_copies)
from stablebptt.flows.linearized import linearized_gradients, policy_gradients
from stablebptt.flows.modes import FLOWS, KEEPS


def flow_losses(dynamics: Dynamics, flows: tuple[str, ...], params: PyTree, initial_states: PyTree,
                control_offsets: PyTree, plan: Plan = Plan()):
    """Mean batch loss once per flow copy (identical values, distinct gradients), and the visited states.

    ``params`` holds one copy per flow (leading axis) where
    ``plan.policy_gradient`` is ``"per-step"``. Differentiated with respect
    to ``control_offsets`` (zeros added to the controls, [T, copies, batch, ...]),
    it gives every flow's adjoint of every control. Returns ``(losses [copies], x_0..x_{T-1}, x_T)``.
    """
    step = multi_adjoint_step(dynamics, flows, plan)
    copies = len(flows)

    def body(state_copies, offsets):
        next_copies, control_copies = step(params, state_copies, offsets)
        return next_copies, (first_copy(state_copies), next_copies, control_copies)

    final, (visited, states, controls) = jax.lax.scan(body, stack_copies(initial_states, copies), control_offsets,
                                                      unroll=plan.unroll)
    # scan stacks time first, [T, copies, batch, ...]; the loss wants one trajectory's [T, ...].
    per_trajectory = jax.vmap(jax.vmap(dynamics.loss, in_axes=(1, 1)), in_axes=(1, 1))(states, controls)
    return per_trajectory.mean(axis=1), visited, first_copy(final)


def flow_gradients(dynamics: Dynamics, flows: tuple[str, ...], params: PyTree, initial_states: PyTree,
                   plan: Plan = Plan()):
    """Mean batch loss and the gradient of every flow from one forward rollout (``flow_window``'s first two).

    Returns:
      ``(loss, grads)`` where each leaf of ``grads`` has a leading axis of
      length ``len(flows)`` in the order of ``flows``.
    """
    # The public entry checks what it is given; the trainer's windows (flow_window) take what make_trainer checked.
    check_dynamics(dynamics)
    if not (isinstance(flows, (tuple, list)) and flows and all(flow in FLOWS for flow in flows)):
        raise InputError(f"flows must name one or more of {', '.join(FLOWS)}, got {flows!r}")
    if not isinstance(plan, Plan):
        raise InputError(f"plan must be a stablebptt.Plan, got {type(plan).__name__}")
    if not all(jnp.ndim(leaf) >= 1 for leaf in jax.tree.leaves(initial_states)):
        raise TaskError("initial_states must be a batch of states, every leaf's leading axis the batch: a leaf has "
                        "none")
    # The parameters against the policy, on shapes alone: a mismatch reads in JAX's terms deep in the window.
    users_call("Dynamics.policy(params, state) fails on the params given and one of initial_states",
               lambda: jax.eval_shape(dynamics.policy, params, one_state_shape(initial_states)))
    window = flow_window(dynamics, flows, params, initial_states, plan)
    return window.loss, window.grads


class WindowGradients(NamedTuple):
    """What one forward rollout of a window gives (``flow_window``)."""

    loss: jax.Array  # mean batch loss
    grads: PyTree  # every flow's gradient, a leading axis of len(flows)
    final: PyTree  # x_T [batch, ...], where a trainer of carried episodes continues from
    visited: PyTree  # x_0..x_{T-1} [T, batch, ...]


def flow_window(dynamics: Dynamics, flows: tuple[str, ...], params: PyTree, initial_states: PyTree,
                plan: Plan = Plan()):
    """Mean batch loss, the gradient of every flow and the states reached, from one forward rollout of a window.

    Args:
      dynamics: the system to differentiate.
      flows: names from ``FLOWS``, e.g. ``("R", "M")``.
      params: policy parameters.
      initial_states: a batch of initial states (leading axis = batch).
      plan: how to differentiate ``dynamics`` (a task's own: ``Task.plan``; a run's: ``Trainer.plan``).

    Returns:
      ``WindowGradients``: ``grads`` as ``flow_gradients``', the batch after ``dynamics.horizon`` steps
      and the states each step started from.
    """
    if plan.step_derivative == "forward":
        return WindowGradients(*linearized_gradients(dynamics, flows, params, initial_states, plan))

    control = jax.eval_shape(jax.vmap(dynamics.policy, in_axes=(None, 0)), params, initial_states)
    offsets = jax.tree.map(lambda a: jnp.zeros((dynamics.horizon, len(flows)) + a.shape, a.dtype), control)
    per_step = plan.policy_gradient == "per-step"

    def total(params, offsets):
        per_flow, visited, final = flow_losses(dynamics, flows, params, initial_states, offsets, plan)
        return per_flow.sum(), (per_flow[0], visited, final)

    (params_grads, control_adjoints), (loss, visited, final) = jax.grad(total, argnums=(0, 1), has_aux=True)(
        stack_copies(params, len(flows)) if per_step else params, offsets)
    if per_step:
        return WindowGradients(loss, params_grads, final, visited)
    return WindowGradients(loss, policy_gradients(dynamics, params, visited, ravel_examples(control_adjoints, 3)),
                           final, visited)


class Trajectory(NamedTuple):
    states: PyTree  # x_1..x_T
    controls: PyTree  # u_0..u_{T-1}


def reference_rollout(dynamics: Dynamics, params: PyTree, initial_state: PyTree, flow: str = "R",
                      plan: Plan = Plan()) -> Trajectory:
    """The rollout with stop_gradient placed literally as in the table above (of ``plan``, only ``unroll`` applies)."""
    cut_sim = not KEEPS[flow][0]
    cut_net = not KEEPS[flow][1]

    def body(state, _):
        control = dynamics.policy(params, jax.lax.stop_gradient(state) if cut_net else state)
        next_state = dynamics.step(jax.lax.stop_gradient(state) if cut_sim else state, control)
        return next_state, (next_state, control)

    _, (states, controls) = jax.lax.scan(body, initial_state, None, length=dynamics.horizon, unroll=plan.unroll)
    return Trajectory(states, controls)


def reference_losses(dynamics: Dynamics, params: PyTree, initial_states: PyTree, flow: str = "R",
                     plan: Plan = Plan()) -> jax.Array:
    """The loss of each trajectory from a batch of initial states."""
    def one(x0):
        trajectory = reference_rollout(dynamics, params, x0, flow, plan)
        return dynamics.loss(trajectory.states, trajectory.controls)

    return jax.vmap(one)(initial_states)


def reference_loss(dynamics: Dynamics, params: PyTree, initial_states: PyTree, flow: str = "R",
                   plan: Plan = Plan()) -> jax.Array:
    """Mean loss over a batch of initial states; differentiate it for the flow's gradient."""
    return reference_losses(dynamics, params, initial_states, flow, plan).mean()
