"""Running observation statistics: batch by batch they equal the statistics of all counted observations
at once; a policy standardised by them takes no gradient through them, and a trainer refreshes them from
exactly the states its windows visited."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stablebptt.engine.config import TrainConfig, seed_array
from stablebptt.engine.observations import (
    CLIP_DEVIATIONS,
    StandardizedNetwork,
    deviation,
    no_observations,
    refresh_from,
    standardized,
    with_observations,
)
from stablebptt.engine.task import Task
from stablebptt.engine.training import make_trainer
from stablebptt.flows.dynamics import Dynamics

from conftest import float64

pytestmark = pytest.mark.fast


def test_statistics_batch_by_batch_are_those_of_every_counted_observation_at_once():
    rng = np.random.default_rng(0)
    batches = [rng.normal([3.0, -200.0, 0.5], [1.0, 50.0, 0.0], size=(n, 3)) for n in (5, 1, 12)]
    counted = [rng.random(len(batch)) < 0.7 for batch in batches]
    counted[1][:] = False  # a batch with nothing counted changes nothing
    with float64():
        statistics = no_observations(3)
        np.testing.assert_array_equal(deviation(statistics), 1.0)  # before any: observations pass unchanged
        np.testing.assert_array_equal(standardized(statistics, jnp.array([0.3, -2.0, 7.0])), [0.3, -2.0, CLIP_DEVIATIONS])
        for batch, mask in zip(batches, counted):
            statistics = with_observations(statistics, jnp.asarray(batch), jnp.asarray(mask))
        every = np.concatenate([batch[mask] for batch, mask in zip(batches, counted)])
        assert float(statistics.count) == len(every)
        np.testing.assert_allclose(statistics.mean, every.mean(axis=0), rtol=1e-12)
        np.testing.assert_allclose(deviation(statistics), every.std(axis=0), rtol=1e-10, atol=1e-12)
        # A constant observation (deviation 0) stays finite; the others are in deviations from the mean.
        scaled = standardized(statistics, jnp.asarray(every[0]))
        assert np.isfinite(np.asarray(scaled)).all()
        np.testing.assert_allclose(scaled[:2], (every[0] - every.mean(axis=0))[:2] / every.std(axis=0)[:2], rtol=1e-10)


RATE = 0.8


def standardized_drift() -> Task:
    """x' = RATE x whatever the action (so the visited states are known in closed form), the loss the
    squared states and actions; the action is theta . (standardised x, 1)."""
    def policy(params, x):
        seen = standardized(params.statistics, jnp.stack([x]))[0]
        return jnp.stack([params.network[0] * seen + params.network[1]])

    dynamics = Dynamics(step=lambda x, u: RATE * x + 0.0 * u[0], policy=policy,
                        loss=lambda states, controls: jnp.sum(states ** 2) + jnp.sum(controls ** 2), horizon=3)
    return Task(name="drift", dynamics=dynamics,
                init_params=lambda key, zero: StandardizedNetwork(jnp.array([0.5, 0.3]), no_observations(1)),
                sample_initial_states=lambda key, n: jax.random.uniform(key, (n,), minval=1.0, maxval=3.0),
                refresh_statistics=refresh_from(lambda x: jnp.stack([x])))


@pytest.mark.parametrize("mode", [pytest.param("R", marks=pytest.mark.slow), "C"])  # both in the full tier
def test_a_trainer_refreshes_the_statistics_from_its_windows_states_and_trains_the_network_alone(mode):
    task = standardized_drift()
    config = TrainConfig(mode=mode, epochs=1, batch=2, train_size=4, test_size=2, lr=1e-2, cosine=False)
    trainer = make_trainer(task, config)
    state = trainer.init(seed_array(config))
    visited = np.asarray(trainer.train_states)[:, None] * RATE ** np.arange(3)  # x_0 .. x_2 of every start
    state, metrics = trainer.epoch(state, trainer.batches, trainer.train_states, trainer.test_states)
    assert bool(metrics["finite"][0])
    statistics = jax.tree.map(lambda a: a[0], state.params.statistics)
    assert float(statistics.count) == visited.size  # two updates of two starts, three states each
    # Exactly the data's statistics: the optimizer did not move them (they take no gradient).
    np.testing.assert_allclose(statistics.mean, [visited.mean()], rtol=1e-5)
    np.testing.assert_allclose(deviation(statistics), [visited.std()], rtol=1e-4)
    assert float(jnp.max(jnp.abs(state.params.network[0] - jnp.array([0.5, 0.3])))) > 1e-4  # the network trains
    grads = jax.grad(lambda p: task.dynamics.policy(p, jnp.float32(2.0))[0])(
        jax.tree.map(lambda a: a[0], state.params))
    assert all(float(jnp.max(jnp.abs(leaf))) == 0 for leaf in jax.tree.leaves(grads.statistics))
