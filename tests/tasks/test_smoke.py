"""Every registered task, built with its defaults at a tiny horizon: finite R, M and S gradients, and
the one-pass R and M (forward-mode step Jacobians where the task uses them) equal to their literal
stop_gradient definition (reverse-mode autodiff of the rollout); S is M's one-step truncation."""
from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from stablebptt import tasks
from stablebptt.flows.gradients import flow_gradients, reference_loss

pytestmark = pytest.mark.fast  # make test-fast: closed forms, invariants, tiny horizons

HORIZON = 3
# Options a task cannot default: the environment task's environment (tests/envs_for_tests.py).
REQUIRED = {"env": {"env": "envs_for_tests:make_cart"}}
FLOWS = ("R", "M", "S")
CHECKED = ("R", "M")  # against their literal definitions


@pytest.mark.parametrize("name", sorted(tasks.entries()))
def test_every_task_gives_finite_flows_equal_to_their_definition(name):
    module = tasks.load(name)
    task = module.make(module.Config(**REQUIRED.get(name, {})))
    dynamics = dataclasses.replace(task.dynamics, horizon=HORIZON)
    # Glorot output layer: with a zero output layer some flows are exactly zero and prove little.
    params = task.init_params(jax.random.PRNGKey(0), False)
    states = task.sample_initial_states(jax.random.PRNGKey(1), 2)

    def both(p, s):  # one program: the one-pass flows and the literal definitions of R and M
        literal = [jax.grad(lambda p: reference_loss(dynamics, p, s, flow))(p) for flow in CHECKED]
        return flow_gradients(dynamics, FLOWS, p, s, task.plan), literal

    (loss, grads), literals = jax.jit(both)(params, states)
    assert np.isfinite(float(loss))
    assert all(np.all(np.isfinite(leaf)) for leaf in jax.tree.leaves(grads)), name
    for index, (flow, literal) in enumerate(zip(CHECKED, literals)):
        one_pass = jax.tree.map(lambda a: a[index], grads)
        for got, expected in zip(jax.tree.leaves(one_pass), jax.tree.leaves(literal)):
            assert np.all(np.isfinite(got)), (name, flow)
            scale = max(float(np.abs(expected).max()), 1e-30)
            np.testing.assert_allclose(got, expected, rtol=2e-3, atol=2e-3 * scale, err_msg=f"{name}, flow {flow}")
    r_norm = sum(float(np.abs(leaf[0]).sum()) for leaf in jax.tree.leaves(grads))
    assert r_norm > 0, f"{name}: the R gradient is exactly zero"
