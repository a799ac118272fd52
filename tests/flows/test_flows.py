"""The gradient flows R, M, S and the combination C: closed forms, definitions, invariants."""

import os
import re

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from stablebptt.engine.memory import plan_memory
from stablebptt.errors import InputError
from stablebptt.flows import adjoint_step
from stablebptt.flows.dynamics import Dynamics, Plan
from stablebptt.flows.gradients import flow_gradients, reference_loss, reference_rollout
from stablebptt.flows.modes import flows_needed, select_flow, sign_agreement, tree_cosine

pytestmark = pytest.mark.fast  # make test-fast: closed forms, invariants, tiny horizons

A, B, T = 0.9, 0.5, 6  # x_{t+1} = A x_t + B u_t, u_t = theta x_t, loss x_T^2 / 2


def linear_dynamics(horizon=T):
    return Dynamics(
        step=lambda x, u: A * x + B * u,
        policy=lambda theta, x: theta * x,
        loss=lambda states, controls: 0.5 * states[-1] ** 2,
        horizon=horizon,
    )


def closed_forms(theta, x0):
    """Hand-derived gradients of the three flows for the scalar linear system."""
    c = A + B * theta
    xs = x0 * c ** np.arange(T + 1)
    regular = xs[T] * T * c ** (T - 1) * B * x0  # d(x_T)/d(theta) through every path
    physics = xs[T] * B * sum(A ** (T - 1 - t) * xs[t] for t in range(T))  # adjoint only via A
    one_step = xs[T] * B * xs[T - 1]  # only the last control reaches the final-state loss
    return {"R": regular, "M": physics, "S": one_step}


@pytest.mark.parametrize("step_derivative", ["reverse", "forward"])
@pytest.mark.parametrize("theta", [-0.7, 0.3])
def test_flows_match_closed_forms(x64, theta, step_derivative):
    x0 = jnp.array([1.3])
    expected = closed_forms(theta, 1.3)
    loss, grads = flow_gradients(linear_dynamics(), ("R", "M", "S"), jnp.array(theta), x0, Plan(step_derivative=step_derivative))
    assert np.isclose(loss, 0.5 * (1.3 * (A + B * theta) ** T) ** 2, rtol=1e-12)
    for index, flow in enumerate(("R", "M", "S")):
        assert np.isclose(grads[index], expected[flow], rtol=1e-12), flow
        # The literal stop_gradient transcription agrees with the closed form too.
        assert np.isclose(jax.grad(reference_loss, argnums=1)(linear_dynamics(), jnp.array(theta), x0, flow),
                          expected[flow], rtol=1e-12), flow


def test_modes_differ_only_in_the_backward_pass():
    dynamics = linear_dynamics()
    trajectories = [reference_rollout(dynamics, 0.4, jnp.array(1.1), flow) for flow in ("R", "M", "S")]
    for trajectory in trajectories[1:]:
        np.testing.assert_array_equal(trajectory.states, trajectories[0].states)
        np.testing.assert_array_equal(trajectory.controls, trajectories[0].controls)
    losses = [flow_gradients(dynamics, flows, jnp.array(0.4), jnp.array([1.1]))[0] for flows in (("R",), ("M",), ("R", "M", "S"))]
    assert losses[0] == losses[1] == losses[2]
    # ... and they do differ there: each flow's gradient its own (the closed forms: test_flows_match_closed_forms).
    _, grads = flow_gradients(dynamics, ("R", "M", "S"), jnp.array(0.4), jnp.array([1.1]))
    assert len({float(g) for g in grads}) == 3, grads


def test_combination_follows_the_sign_rule():
    g_m = {"w": jnp.array([1.0, -2.0, 3.0, 0.0, -1.0])}
    g_r = {"w": jnp.array([4.0, 5.0, -6.0, 0.0, -0.5])}
    np.testing.assert_array_equal(sign_agreement(g_m, g_r)["w"], [1.0, 0.0, 0.0, 0.0, -1.0])


def test_combination_invariants():
    g = {"a": jax.random.normal(jax.random.PRNGKey(0), (7, 3)), "b": jax.random.normal(jax.random.PRNGKey(1), (5,))}
    same = sign_agreement(g, g)
    opposite = sign_agreement(g, jax.tree.map(jnp.negative, g))
    for leaf, kept, cancelled in zip(jax.tree.leaves(g), jax.tree.leaves(same), jax.tree.leaves(opposite)):
        np.testing.assert_array_equal(kept, leaf)
        np.testing.assert_array_equal(cancelled, jnp.zeros_like(leaf))
    assert np.isclose(tree_cosine(g, g), 1.0) and np.isclose(tree_cosine(g, jax.tree.map(jnp.negative, g)), -1.0)


def test_select_flow_heads_one_optax_chain():
    flows = ("R", "M")
    stacked = {"w": jnp.array([[1.0, -2.0, 0.5], [3.0, 1.0, 0.25]])}  # rows: R, M
    params = {"w": jnp.zeros(3)}
    for mode, expected in (("R", [1.0, -2.0, 0.5]), ("M", [3.0, 1.0, 0.25]), ("C", [3.0, 0.0, 0.25])):
        chain = optax.chain(select_flow(mode, flows), optax.clip(0.5), optax.sgd(1.0))
        updates, _ = chain.update(stacked, chain.init(params), params)
        np.testing.assert_allclose(updates["w"], -np.clip(expected, -0.5, 0.5))
    with pytest.raises(InputError, match="needs flows"):
        select_flow("S", flows)


def test_flows_needed():
    assert flows_needed("C", with_cosine=False) == ("R", "M")
    assert flows_needed("S", with_cosine=True) == ("R", "M", "S")
    assert flows_needed("R", with_cosine=False) == ("R",)
    with pytest.raises(InputError, match="unknown mode 'X'"):
        flows_needed("X")


def test_flow_gradients_name_what_they_are_given_wrong():
    dynamics = Dynamics(policy=lambda p, x: p * x, step=lambda x, u: x + u, loss=lambda xs, us: jnp.sum(xs ** 2),
                        horizon=2)
    for flows, plan, words in ((("X",), Plan(), "flows must name one or more of R, M, S, got ('X',)"),
                               ((), Plan(), "flows must name one or more of R, M, S, got ()"),
                               (("R",), "forward", "plan must be a stablebptt.Plan, got str")):
        with pytest.raises(InputError, match=re.escape(words)):
            flow_gradients(dynamics, flows, jnp.array(0.4), jnp.array([1.1]), plan)


@pytest.mark.parametrize("step_derivative, unroll, memory", [
    ("reverse", 1, {}), ("forward", 1, {}), ("forward", 5, {}),
    ("forward", 1, {"jacobian_chunk": 8}), ("reverse", 1, {"rematerialize": True}),
    ("reverse", 5, {"policy_gradient": "per-step", "rematerialize": True})])
def test_one_pass_equals_reference_on_a_nonlinear_system_with_control_cost(x64, step_derivative, unroll, memory):
    """Nonlinear step on a pytree state, MLP-like policy, a loss on every state and on the controls.

    unroll=5 does not divide the horizon: the unrolled loop's remainder must be right too. The
    memory plan's settings (Jacobians in chunks of 8 of the 48 examples, steps recomputed in the
    backward pass) change no number either, nor does where reverse mode forms the parameter gradient.
    """
    assert_one_pass_equals_reference(step_derivative, unroll, memory)


@pytest.mark.parametrize("memory", [{}, {"policy_gradient": "per-step", "rematerialize": True}])
def test_flows_pulled_back_batched_give_the_reference_gradients_too(x64, monkeypatch, memory):
    """A CPU pulls the flows' cotangents back in turn (``adjoint_step.pullbacks_in_turn``), which the test
    above runs; a GPU batches them over the flows, run here."""
    monkeypatch.setattr(adjoint_step, "pullbacks_in_turn", lambda: False)
    assert_one_pass_equals_reference("reverse", 1, memory)


def assert_one_pass_equals_reference(step_derivative, unroll, memory):
    dynamics = Dynamics(
        step=lambda s, u: (s[0] + 0.1 * jnp.sin(s[1][::-1]) + 0.2 * u, s[1] + 0.1 * s[0] * jnp.cos(u.sum())),
        policy=lambda p, s: jnp.tanh(jnp.concatenate(s) @ p["w"]) @ p["v"],
        loss=lambda states, controls: jnp.mean(states[0] ** 2) + jnp.mean(states[1][-1] ** 2) + 0.3 * jnp.mean(controls**2),
        horizon=12,
    )
    plan = Plan(step_derivative=step_derivative, unroll=unroll, **memory)
    key_w, key_v, key_x = jax.random.split(jax.random.PRNGKey(3), 3)
    params = {"w": jax.random.normal(key_w, (4, 5)), "v": jax.random.normal(key_v, (5, 2))}
    x0 = tuple(jax.random.normal(key_x, (2, 4, 2)))
    # Jitted, as training runs them: eagerly, every operation would be compiled apart.
    _, grads = jax.jit(lambda p, x: flow_gradients(dynamics, ("R", "M", "S"), p, x, plan))(params, x0)
    for index, flow in enumerate(("R", "M", "S")):
        expected = jax.jit(jax.grad(lambda p, x: reference_loss(dynamics, p, x, flow)))(params, x0)
        for fast, slow in zip(jax.tree.leaves(grads), jax.tree.leaves(expected)):
            np.testing.assert_allclose(fast[index], slow, rtol=1e-10, atol=1e-12)


def test_the_combination_never_points_uphill():
    """Every kept component of C agrees in sign with g_R, so <C, g_R> >= 0: C is a descent direction
    even where M rotates away from it (the mechanism behind scripts/toy.py)."""
    g_m = jax.random.normal(jax.random.PRNGKey(5), (1000, 6))
    g_r = jax.random.normal(jax.random.PRNGKey(6), (1000, 6))
    combined = sign_agreement(g_m, g_r)
    assert np.all(np.sum(combined * g_r, axis=1) >= 0)
    assert np.all((combined == 0) | (combined == g_m))


def test_the_memory_plan_chunks_recomputes_or_refuses_as_the_budget_shrinks():
    step = lambda x, u: jnp.tanh(x @ jnp.ones((16, 16)) + u.sum())
    state, control = jnp.ones(16), jnp.ones(2)
    plenty = plan_memory(step, state, control, horizon=10, batch=8, step_derivative="forward", tangents=18,
                         budget=2**40)
    assert plenty.jacobian_chunk is None and plenty.estimate > 0
    one_example = plenty.estimate // 80
    chunked = plan_memory(step, state, control, 10, 8, "forward", 18, budget=int(7.5 * one_example))
    assert chunked.jacobian_chunk == 5  # the largest divisor of 80 examples that fits 7.5 of them
    with pytest.raises(InputError, match="Plan.step_derivative to 'reverse'"):
        plan_memory(step, state, control, 10, 8, "forward", 18, budget=one_example - 1)
    stored = plan_memory(step, state, control, 10, 8, "reverse", 18, budget=2**40)
    assert not stored.rematerialize
    assert plan_memory(step, state, control, 10, 8, "reverse", 18, budget=stored.estimate - 1).rematerialize
    with pytest.raises(InputError, match="TrainConfig.batch"):
        plan_memory(step, state, control, 10, 8, "reverse", 18, budget=1)
    # Seeds batched in one program hold a path each at once: 5 seeds in a budget that fits one recompute.
    five = plan_memory(step, state, control, 10, 8, "reverse", 18, budget=stored.estimate, copies=5)
    assert five.rematerialize and five.estimate == 5 * stored.estimate
    assert plan_memory(step, state, control, 10, 8, "forward", 18, budget=int(7.5 * one_example),
                       copies=5).jacobian_chunk == 1  # 1.5 examples of each seed's fit: chunks of one
    with pytest.raises(InputError, match="--seed-batching map"):
        plan_memory(step, state, control, 10, 8, "forward", 18, budget=2 * one_example, copies=5)
    # Split over 2 devices, each holds half of every path in its own budget: the stored steps fit
    # where on one device they are recomputed; 7 examples fit a device, so a chunk is 10 of the 80 (the
    # largest divisor within 14 that splits evenly), 5 on each device.
    halved = plan_memory(step, state, control, 10, 8, "reverse", 18, budget=stored.estimate // 2, devices=2)
    assert not halved.rematerialize and halved.estimate == stored.estimate // 2
    assert plan_memory(step, state, control, 10, 8, "reverse", 18, budget=stored.estimate // 2).rematerialize
    assert plan_memory(step, state, control, 10, 8, "forward", 18, budget=int(7.5 * one_example),
                       devices=2).jacobian_chunk == 10


def test_the_memory_plan_budgets_an_accelerators_free_memory_not_the_hosts(monkeypatch):
    from stablebptt.engine import memory

    class Accelerator:  # a GPU's allocator as JAX reports it
        platform = "gpu"

        def memory_stats(self):
            return {"bytes_limit": 24 * 2**30, "bytes_in_use": 4 * 2**30}

    host = memory.available_bytes()  # this machine's CPU: the OS's figure
    assert 0 < host <= os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    monkeypatch.setattr(jax, "devices", lambda *a: [Accelerator()])
    assert memory.available_bytes() == 20 * 2**30


def counted_dynamics():
    """x carries a step counter, a PRNG key and a flag beside its floats: an environment's state in small."""
    def step(state, u):
        noise = 0.01 * jax.random.normal(jax.random.fold_in(state["key"], state["count"]), (2,))
        x = jnp.where(state["flag"], A, 0.8) * state["x"] + B * u + noise
        return {"x": x, "count": state["count"] + 1, "key": state["key"], "flag": x[0] > 0}

    return Dynamics(step=step, policy=lambda theta, s: jnp.tanh(theta @ s["x"]) * (1 + 0.1 * s["count"]),
                    loss=lambda states, controls: jnp.sum(states["x"] ** 2) + 0.1 * jnp.sum(controls ** 2),
                    horizon=T)


@pytest.mark.parametrize("step_derivative", ["reverse", "forward"])
@pytest.mark.parametrize("policy_gradient", ["batched", "per-step"])
def test_states_with_integer_bool_and_key_leaves(x64, step_derivative, policy_gradient):
    """Such leaves pass through untouched; every flow still equals its stop_gradient definition."""
    dynamics, plan = counted_dynamics(), Plan(step_derivative=step_derivative, policy_gradient=policy_gradient)
    theta = jnp.array([[0.3, -0.2], [0.1, 0.4]])
    states = {"x": jax.random.normal(jax.random.PRNGKey(0), (3, 2)), "count": jnp.arange(3, dtype=jnp.int32),
              "key": jax.random.split(jax.random.key(7), 3), "flag": jnp.array([True, False, True])}
    loss, grads = jax.jit(lambda p, s: flow_gradients(dynamics, ("R", "M", "S"), p, s, plan))(theta, states)
    assert np.isclose(loss, jax.jit(lambda p, s: reference_loss(dynamics, p, s))(theta, states), rtol=1e-12)
    for index, flow in enumerate(("R", "M", "S")):
        expected = jax.jit(jax.grad(lambda p, s: reference_loss(dynamics, p, s, flow)))(theta, states)
        np.testing.assert_allclose(grads[index], expected, rtol=1e-10, atol=1e-14, err_msg=flow)
