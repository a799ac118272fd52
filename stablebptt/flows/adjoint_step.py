"""The reverse-mode step of several flows at once (``Plan.step_derivative == "reverse"``).

Every step of the rollout is a ``custom_vjp`` that stores the simulator's and the policy's pullbacks
once, for the whole batch, and in the reverse pass pulls back one cotangent per flow through them
(``stablebptt.flows.gradients.flow_losses`` scans it): batched over the flows, or in turn on a CPU.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from stablebptt.flows.dynamics import Dynamics, Plan, first_copy, join, split, split_cotangent, stack_copies
from stablebptt.flows.modes import KEEPS


def pullbacks_in_turn() -> bool:
    """Whether the reverse pass pulls the flows' cotangents back one after another (on a CPU) rather
    than batched over the flows."""
    return jax.default_backend() == "cpu"


def multi_adjoint_step(dynamics: Dynamics, flows: tuple[str, ...], plan: Plan = Plan()):
    """One simulator step of a whole batch whose reverse pass carries one adjoint per flow (``"reverse"``).

    ``step(params, state_copies, control_offsets)``: states hold ``len(flows)``
    identical copies along a leading axis, then the batch; only the cotangents
    of the copies differ. The forward pass computes the step once. The batch
    lives inside the custom_vjp on purpose: one batched pullback per step,
    not one per example.

    The controls are ``policy(params, x) + control_offsets`` (the offsets are
    zeros), so the offsets' cotangent is each flow's adjoint of every control.
    With ``plan.policy_gradient == "batched"`` the reverse pass returns no
    parameter cotangent: the parameter gradient is one batched pullback over
    all visited states afterwards (``policy_gradients``), and the policy is
    pulled back per step only for the flows whose state cotangent passes
    through it (R). With ``"per-step"`` each step returns every flow's
    parameter cotangent (``params`` then holds one copy per flow).
    """
    copies = len(flows)
    # NumPy, not jnp: constants created under a trace would be tracers closed
    # over by the custom_vjp.
    keep_sim = np.array([KEEPS[f][0] for f in flows])
    through_net = [index for index, f in enumerate(flows) if KEEPS[f][1]]
    per_step = plan.policy_gradient == "per-step"
    batch_policy = jax.vmap(dynamics.policy, in_axes=(None, 0))
    batch_step = jax.vmap(dynamics.step)

    def select(mask, a):
        # where, not multiply: a cut path must not turn inf into NaN.
        return jnp.where(mask.reshape((copies,) + (1,) * (a.ndim - 1)), a, jnp.zeros_like(a))

    def forward(params, states):
        # Only float leaves are differentiated; the others (counters, keys, indices) ride along.
        parts = split(states)
        policy = batch_policy if per_step else lambda params, s: batch_policy(jax.lax.stop_gradient(params), s)
        controls, policy_pullback = jax.vjp(lambda p, floats: policy(p, join(parts, floats)), params, parts.floats)

        def float_step(floats, controls):
            reached = split(batch_step(join(parts, floats), controls))
            return reached.floats, reached.others

        next_floats, step_pullback, next_others = jax.vjp(float_step, parts.floats, controls, has_aux=True)
        return join(parts, next_floats, next_others), controls, (policy_pullback, step_pullback)

    def outputs(next_states, controls, control_offsets):
        return stack_copies(next_states, copies), jax.tree.map(jnp.add, stack_copies(controls, copies), control_offsets)

    params_of = first_copy if per_step else lambda params: params

    def values(params, state_copies, control_offsets):
        # The values alone: tracing ``forward`` would linearize the simulator for pullbacks never used.
        states = first_copy(state_copies)
        controls = batch_policy(params_of(params), states)
        return outputs(batch_step(states, controls), controls, control_offsets)

    step = jax.custom_vjp(values)  # under differentiation only ``step_fwd`` runs

    def step_fwd(params, state_copies, control_offsets):
        states = first_copy(state_copies)
        if plan.rematerialize:  # the backward pass linearizes the step again: here its values alone
            return values(params, state_copies, control_offsets), ((params_of(params), states), params)
        next_states, controls, pullbacks = forward(params_of(params), states)
        return outputs(next_states, controls, control_offsets), (pullbacks, params)

    def step_bwd(saved, cotangents):
        residuals, params = saved
        policy_pullback, step_pullback = forward(*residuals)[2] if plan.rematerialize else residuals
        next_state_ct, control_ct = cotangents
        # Leaves without a derivative get float0 cotangents, which mark them here.
        parts = split_cotangent(next_state_ct)
        # One pullback per flow: in turn on a CPU (each runs as the single-flow program, and the update
        # ran 2-16% faster than batched: benchmarks/update_program.py), batched over the flows elsewhere.
        pulled = jax.lax.map(step_pullback, parts.floats) if pullbacks_in_turn() else jax.vmap(step_pullback)(parts.floats)
        state_ct_sim, control_ct_sim = pulled
        control_ct = jax.tree.map(jnp.add, control_ct, control_ct_sim)
        state_ct = [select(keep_sim, sim) for sim in state_ct_sim]
        if per_step:  # one pullback per flow gives its parameter cotangent and, for R, its state's
            params_ct, net = jax.vmap(policy_pullback)(control_ct)
            net = [select(np.isin(np.arange(copies), through_net), a) for a in net]
            return params_ct, join(parts, [a + b for a, b in zip(state_ct, net)]), control_ct
        if through_net:
            rows = np.array(through_net)
            net = jax.vmap(lambda ct: policy_pullback(ct)[1])(jax.tree.map(lambda a: a[rows], control_ct))
            state_ct = [total.at[rows].add(part) for total, part in zip(state_ct, net)]
        return jax.tree.map(jnp.zeros_like, params), join(parts, state_ct), control_ct

    step.defvjp(step_fwd, step_bwd)
    return step
