"""The env's step traced once for a task's checks and programs (``jit_traced_once``): the checks trace
it where no abstract mesh is set, the update's custom derivative traces its forward pass again inside a
program JAX evaluates under its empty mesh, and JAX keys a jit's traces on that mesh. One trace, and
the derivative through it is the plain rollout's."""
import jax
import numpy as np

from stablebptt.envs.adapter import env_task
from stablebptt.flows.gradients import flow_gradients, reference_losses

from envs_for_tests import Ball


class CountedBall(Ball):
    """The ball, counting the traces of its step (its Python runs once a trace)."""

    def __init__(self):
        super().__init__()
        self.traced = []  # one list for the copies a task makes of its env

    def step(self, state, action):
        self.traced.append(True)
        return super().step(state, action)


def test_the_checks_and_the_update_share_one_trace_of_the_envs_step():
    env = CountedBall()
    task = env_task(env, horizon=3, diagnose=False)
    params = task.init_params(jax.random.PRNGKey(0), False)
    states = task.sample_initial_states(jax.random.PRNGKey(1), 4)
    one = jax.tree.map(lambda a: a[0], states)
    jax.eval_shape(task.dynamics.step, one, task.dynamics.policy(params, one))  # as a check traces it
    assert len(env.traced) == 1
    _, grads = jax.jit(lambda p, x: flow_gradients(task.dynamics, ("R", "M"), p, x, task.plan))(params, states)
    assert len(env.traced) == 1  # the window's forward pass and its custom derivative found that trace
    plain = jax.jit(jax.grad(lambda p: reference_losses(task.dynamics, p, states, "R", task.plan).mean()))(params)
    for flows_leaf, plain_leaf in zip(jax.tree.leaves(grads), jax.tree.leaves(plain)):
        np.testing.assert_allclose(flows_leaf[0], plain_leaf, rtol=1e-4, atol=1e-7)
