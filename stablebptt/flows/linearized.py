"""Step Jacobians by forward mode and the flows from them (``Plan.step_derivative == "forward"``).

The rollout stores only states and controls. A step's Jacobian depends on nothing but its own
(x_t, u_t), so the Jacobians of ALL steps are built afterwards in one batched forward-mode pass
(``step_jacobians``) and the reverse pass becomes a linear recurrence of small matrix products, one
adjoint per flow. The policy's parameter gradient is then one batched pullback over every visited
state (``policy_gradients``, which the reverse-mode path uses too).
"""
from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from stablebptt.flows.dynamics import (
    Dynamics,
    KnownColumns,
    Plan,
    PyTree,
    check_known_columns,
    join,
    merge_axes,
    ravel_examples,
    split,
    stack_copies,
)
from stablebptt.flows.modes import KEEPS


def step_jacobians(step, states: PyTree, controls: PyTree, known: KnownColumns | None = None,
                   chunk: int | None = None, per_input: bool = True,
                   chunk_placement: Callable[[PyTree], PyTree] | None = None) -> tuple[jax.Array, jax.Array]:
    """Jacobians of ``step`` at every example of a batch, by forward mode.

    With ``per_input`` (the default), one forward pass per input leaf (a state
    leaf such as qpos or qvel, or the control), with the other leaves held
    fixed. A simulator therefore sees which inputs vary (a ``custom_jvp`` with
    ``symbolic_zeros=True`` gets symbolic zeros for the others) and can skip the
    stages they do not reach: velocity tangents need no kinematics, control
    tangents only the actuators. Without it, one pass pushes every tangent at
    once: more work per tangent, but one copy of the differentiated step in the
    program, which compiles several times faster for large scenes. Columns in
    ``known`` are copied, not computed. ``chunk`` examples at a time (default:
    all) bound the memory; ``chunk_placement`` (``Plan.chunk_placement``) places
    each chunk's examples where ``chunk`` divides their number.

    Returns:
      ``(state_jacobian [batch, state, state], control_jacobian [batch, state, control])``
      over the flattened state and control pytrees (``ravel_pytree`` order of the state's float
      leaves; its other leaves have no derivative).
    """
    state_size = sum(leaf.size for leaf in split(jax.tree.map(lambda a: a[0], states)).floats)  # the output is a state too
    if known is not None:
        check_known_columns(known, state_size)
    known_at = {} if known is None else {int(i): np.asarray(c) for i, c in zip(known.indices, np.transpose(known.columns))}

    def one(state, control):
        parts = split(state)  # leaves without a derivative are held, not differentiated
        leaves, treedef = jax.tree.flatten((parts.floats, control))
        sizes = [leaf.size for leaf in leaves]
        offsets = np.cumsum([0] + sizes)
        # Input groups pushed together: each leaf alone, or all leaves in one pass.
        groups = [[index] for index in range(len(leaves))] if per_input else [list(range(len(leaves)))]
        blocks = []
        for group in groups:
            columns_of_group = [offsets[index] + k for index in group for k in range(sizes[index])]
            copied = np.zeros((state_size, len(columns_of_group)), np.result_type(*[leaves[i].dtype for i in group]))
            free = []
            for position, column in enumerate(columns_of_group):
                if column in known_at:  # only state columns are ever known
                    copied[:, position] = known_at[column]
                else:
                    free.append(position)
            if not free:
                blocks.append(jnp.asarray(copied))
                continue

            def of_group(flat, group=group):  # step's flat output as a function of the group's inputs
                inputs, start = list(leaves), 0
                for index in group:
                    inputs[index] = flat[start:start + sizes[index]].reshape(leaves[index].shape)
                    start += sizes[index]
                floats, control = jax.tree.unflatten(treedef, inputs)
                return ravel_pytree(split(step(join(parts, floats), control)).floats)[0]

            point = jnp.concatenate([leaves[index].ravel() for index in group])
            # Constant unit tangents for the free entries only: no scatter of a tangent to trace.
            basis = np.eye(len(columns_of_group), dtype=copied.dtype)[free]
            columns = jax.vmap(lambda tangent: jax.jvp(of_group, (point,), (tangent,))[1], out_axes=1)(basis)
            if len(free) < len(columns_of_group):
                columns = copied + jnp.matmul(columns, basis, precision=jax.lax.Precision.HIGHEST)
            blocks.append(columns)
        jacobian = jnp.concatenate(blocks, axis=1)  # columns in ravel_pytree order of (state, control)
        return jacobian[:, :state_size], jacobian[:, state_size:]

    if chunk is None:
        return jax.vmap(one)(states, controls)
    examples = jax.tree.leaves(states)[0].shape[0]
    if chunk_placement is None or examples % chunk:
        return jax.lax.map(lambda example: one(*example), (states, controls), batch_size=chunk)
    chunks = jax.tree.map(lambda a: a.reshape((examples // chunk, chunk) + a.shape[1:]), (states, controls))
    state_jacobian, control_jacobian = jax.lax.map(lambda pair: jax.vmap(one)(*chunk_placement(pair)), chunks)
    whole = lambda a: a.reshape((examples,) + a.shape[2:])  # noqa: E731
    return whole(state_jacobian), whole(control_jacobian)



def linearized_gradients(dynamics: Dynamics, flows: tuple[str, ...], params: PyTree, initial_states: PyTree,
                         plan: Plan = Plan()):
    """``flow_window`` by rollout, batched step Jacobians and an adjoint recurrence (``"forward"``)."""
    horizon, batch_size = dynamics.horizon, jax.tree.leaves(initial_states)[0].shape[0]
    batch_policy = jax.vmap(dynamics.policy, in_axes=(None, 0))
    batch_step = jax.vmap(dynamics.step)

    def advance(states, _):
        controls = batch_policy(params, states)
        return batch_step(states, controls), (states, controls)

    final, (visited, controls) = jax.lax.scan(advance, initial_states, None, length=horizon, unroll=plan.unroll)
    # visited holds x_0..x_{T-1}, [T, batch, ...]; the loss sees x_1..x_T.
    reached = jax.tree.map(lambda past, last: jnp.concatenate([past[1:], last[None]]), visited, final)

    reached_parts = split(reached)

    def batch_loss(floats, controls):
        return jax.vmap(dynamics.loss, in_axes=(1, 1))(join(reached_parts, floats), controls).mean()

    loss, (state_grad, control_grad) = jax.value_and_grad(batch_loss, argnums=(0, 1))(reached_parts.floats, controls)
    state_grad, control_grad = ravel_examples(state_grad, 2), ravel_examples(control_grad, 2)

    # Every step's Jacobians in one batched pass over [T * batch] examples.
    state_jacobian, control_jacobian = step_jacobians(dynamics.step, merge_axes(visited, 2), merge_axes(controls, 2),
                                                       plan.known_columns, plan.jacobian_chunk,
                                                       plan.jacobian_per_input, plan.chunk_placement)
    unmerge = lambda a: a.reshape((horizon, batch_size) + a.shape[1:])
    state_jacobian, control_jacobian = unmerge(state_jacobian), unmerge(control_jacobian)

    visited_parts = split(visited)
    unravel_floats = ravel_pytree([a[0, 0] for a in visited_parts.floats])[1]
    flat_visited = ravel_examples(visited_parts.floats, 2)

    def flat_policy(params, flat_state, others):
        return ravel_pytree(dynamics.policy(params, join(visited_parts, unravel_floats(flat_state), others)))[0]

    policy_jacobian = None
    if "R" in flows:  # only R pulls adjoints back through the policy's input
        state_size, control_size = flat_visited.shape[-1], control_grad.shape[-1]
        jacobian = jax.jacrev if control_size < state_size else jax.jacfwd
        policy_jacobian = jax.vmap(jax.vmap(jacobian(flat_policy, argnums=1), in_axes=(None, 0, 0)),
                                   in_axes=(None, 0, 0))(params, flat_visited, visited_parts.others)  # [T, batch, control, state]

    copies = len(flows)
    keep_sim = np.array([KEEPS[f][0] for f in flows]).reshape(copies, 1, 1)
    keep_net = np.array([KEEPS[f][1] for f in flows]).reshape(copies, 1, 1)

    def vector_times_jacobian(vectors, jacobians):
        """[copies, batch, rows] x [batch, rows, columns] -> [copies, batch, columns].

        Multiply and sum, not a matrix product: XLA fuses the products of one
        step into a few loops in full float32 (GPUs would take TF32 matmuls),
        where batched matrix products of a few rows each cost a library call apiece.
        """
        return jnp.sum(vectors[..., :, None] * jacobians[None], axis=-2)

    def pull_back(adjoint, step):
        """From the adjoint of x_{t+1} per flow [copies, batch, state] to that of x_t, and u_t's."""
        state_jac, control_jac, policy_jac, direct_state, direct_control = step
        control_adjoint = direct_control + vector_times_jacobian(adjoint, control_jac)
        through_sim = vector_times_jacobian(adjoint, state_jac)
        # where, not multiply: a cut path must not turn inf into NaN.
        state_adjoint = direct_state + jnp.where(keep_sim, through_sim, 0.0)
        if policy_jac is not None:
            through_net = vector_times_jacobian(control_adjoint, policy_jac)
            state_adjoint = state_adjoint + jnp.where(keep_net, through_net, 0.0)
        return state_adjoint, control_adjoint

    # The loss's direct gradient on x_t (none on x_0, which is not a result of the rollout).
    direct_state = jnp.concatenate([jnp.zeros_like(state_grad[:1]), state_grad[:-1]])
    _, control_adjoints = jax.lax.scan(
        pull_back, stack_copies(state_grad[-1], copies),
        (state_jacobian, control_jacobian, policy_jacobian, direct_state, control_grad),
        reverse=True, unroll=plan.unroll)  # [T, copies, batch, control]

    return loss, policy_gradients(dynamics, params, visited, control_adjoints), final, visited


def policy_gradients(dynamics: Dynamics, params: PyTree, visited: PyTree, control_adjoints: jax.Array) -> PyTree:
    """Each flow's parameter gradient: the sum over steps and examples of (du_t/dparams)^T adjoint(u_t).

    One batched pullback over every visited state (``visited``: x_0..x_{T-1},
    [T, batch, ...]), one per flow (``control_adjoints``: [T, copies, batch,
    control], flattened controls): a few large matrix products instead of small
    ones per step.
    """
    horizon, copies, batch_size = control_adjoints.shape[:3]
    examples = merge_axes(visited, 2)  # [T * batch, ...], leaves without a derivative included

    def flat_controls(params):
        return ravel_examples(jax.vmap(dynamics.policy, in_axes=(None, 0))(params, examples), 1)

    _, policy_pullback = jax.vjp(flat_controls, params)
    per_flow = jnp.moveaxis(control_adjoints, 1, 0).reshape((copies, horizon * batch_size, -1))
    return jax.vmap(lambda adjoint: policy_pullback(adjoint)[0])(per_flow)

