"""Physics and gradient invariants of the quantum-control task."""
from __future__ import annotations

import argparse
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stablebptt import tasks
from stablebptt.cli import add_options
from stablebptt.engine.config import TrainConfig, seed_array
from stablebptt.engine.training import make_trainer
from stablebptt.errors import InputError
from stablebptt.flows.gradients import flow_gradients, reference_loss, reference_rollout
from stablebptt.flows.modes import FLOWS
from stablebptt.tasks import quantum

pytestmark = pytest.mark.fast  # make test-fast: closed forms, invariants, tiny horizons

PHYSICS = quantum.Physics()
LONG = 10_000  # steps of the long evolutions


@pytest.fixture(scope="module")
def task():
    return quantum.make(quantum.Config())


@pytest.fixture(scope="module")
def params(task):
    """Glorot output layer: a nonzero policy (float32)."""
    return task.init_params(jax.random.PRNGKey(1), False)


@pytest.fixture(scope="module")
def states(task):
    return task.sample_initial_states(jax.random.PRNGKey(2), 16)


def float64(tree):
    """A float32 pytree in float64; call inside ``jax.enable_x64(True)``."""
    return jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), tree)


@pytest.fixture(scope="module")
def evolve(task):
    """Jitted ``(states [B, nx, 2], controls [B, n]) -> squared norms and overlaps with e_1..e_5, [B, n, ...]``.

    One compiled function per (dtype, shape), shared by the norm and eigenstate tests.
    """
    basis = np.stack([quantum.eigenstate(n, PHYSICS.nx) for n in range(1, 6)])

    def one(state, controls):
        def body(state, control):
            state = task.dynamics.step(state, control)
            psi = quantum.to_complex(state)
            overlaps = jnp.sum(jnp.asarray(basis, psi.dtype) * psi, axis=-1)  # no matmul: GPUs round those to TF32
            return state, (jnp.sum(state**2), overlaps)

        return jax.lax.scan(body, state, controls)[1]

    return jax.jit(jax.vmap(one))


def random_controls(key, count, steps, dtype):
    """Controls of order 5: tilts comparable to the level spacing, far from zero."""
    return 5.0 * jax.random.normal(key, (count, steps), dtype)


def norm_drift(states, evolve):
    controls = random_controls(jax.random.PRNGKey(1), len(states), LONG, states.dtype)
    norms, _ = evolve(states, controls)
    return float(jnp.max(jnp.abs(norms - 1.0)))


def test_norm_preserved_float32(states, evolve):
    # Crank-Nicolson is a Cayley transform of a Hermitian H: unitary up to rounding.
    assert norm_drift(states[:4], evolve) < 1e-4


def test_norm_preserved_float64(states, evolve):
    with jax.enable_x64(True):
        states = float64(states[:4])
        states = states / jnp.linalg.norm(states, axis=(1, 2), keepdims=True)  # drop the float32 rounding
        assert norm_drift(states, evolve) < 1e-10


def test_tridiagonal_solve_values_gradients_and_batching():
    with jax.enable_x64(True):
        m = 12
        keys = jax.random.split(jax.random.PRNGKey(20), 8)
        complex_normal = lambda k, shape: jax.lax.complex(jax.random.normal(k, shape), jax.random.normal(jax.random.fold_in(k, 1), shape))
        diagonal, off, rhs, weights = (complex_normal(k, (m,)) for k in keys[:4])
        diagonal = diagonal + 4.0  # well conditioned
        dense = jnp.diag(diagonal) + jnp.diag(off[:-1], 1) + jnp.diag(off[:-1], -1)
        np.testing.assert_allclose(quantum.symmetric_tridiagonal_solve(diagonal, off, rhs), jnp.linalg.solve(dense, rhs), atol=1e-12)

        # The hand-written reverse pass against JAX's derivative of the dense solve, for a real loss.
        def real_loss(solve):
            return lambda d, o, b: jnp.sum(jnp.abs(weights * solve(d, o, b)) ** 2)
        dense_solve = lambda d, o, b: jnp.linalg.solve(jnp.diag(d) + jnp.diag(o[:-1], 1) + jnp.diag(o[:-1], -1), b)
        ours = jax.jit(jax.grad(real_loss(quantum.symmetric_tridiagonal_solve), argnums=(0, 1, 2)))(diagonal, off, rhs)
        reference = jax.jit(jax.grad(real_loss(dense_solve), argnums=(0, 1, 2)))(diagonal, off, rhs)
        for a, b in zip(ours, reference):
            np.testing.assert_allclose(a[: m - 1], b[: m - 1], atol=1e-10)  # off's last entry is unused
        np.testing.assert_allclose(ours[0][-1], reference[0][-1], atol=1e-10)

        # Nested vmap with shared (unbatched) diagonals, the pattern of the flows' adjoint copies.
        diagonals = diagonal + jnp.arange(3.0)[:, None]
        rhss = complex_normal(keys[4], (2, m))
        batched = jax.jit(jax.vmap(lambda d: jax.vmap(lambda b: quantum.symmetric_tridiagonal_solve(d, off, b))(rhss)))(diagonals)
        dense = np.asarray(dense - jnp.diag(diagonal))
        for i, d in enumerate(np.asarray(diagonals)):
            for j, b in enumerate(np.asarray(rhss)):
                np.testing.assert_allclose(batched[i, j], np.linalg.solve(dense + np.diag(d), b), atol=1e-12)


def test_eigenstates_orthonormal():
    basis = np.stack([quantum.eigenstate(n, PHYSICS.nx) for n in range(1, PHYSICS.nx + 1)])
    np.testing.assert_allclose(basis @ basis.T, np.eye(PHYSICS.nx), atol=1e-12)


def test_eigenstates_diagonalise_the_laplacian():
    nx, dx = PHYSICS.nx, PHYSICS.dx
    laplacian = (np.diag(np.full(nx, -2.0)) + np.diag(np.ones(nx - 1), 1) + np.diag(np.ones(nx - 1), -1)) / dx**2
    for n in (1, 3, 5):
        e = quantum.eigenstate(n, nx)
        energy = (2 - 2 * np.cos(np.pi * n / (nx + 1))) / dx**2
        np.testing.assert_allclose(-laplacian @ e, energy * e, atol=1e-9 * energy)


def test_eigenstate_stays_under_zero_control(task, evolve):
    with jax.enable_x64(True):
        steps, dt, dx = 256, quantum.Config().dt, PHYSICS.dx
        states = jnp.asarray(np.stack([quantum.to_real(jnp.asarray(quantum.eigenstate(n, PHYSICS.nx) + 0j)) for n in range(1, 6)]))
        _, overlaps = evolve(states, jnp.zeros((5, steps)))
        diagonal = jnp.diagonal(overlaps, axis1=0, axis2=2)  # <e_n|psi_t> of the run started in e_n: [steps, 5]
        np.testing.assert_allclose(jnp.abs(diagonal), 1.0, atol=1e-10)
        # The phase is the Cayley factor of the eigenvalue, once per step.
        energy = (2 - 2 * np.cos(np.pi * np.arange(1, 6) / (PHYSICS.nx + 1))) / dx**2
        factor = (1 - 0.5j * dt * energy) / (1 + 0.5j * dt * energy)
        expected = factor[None, :] ** np.arange(1, steps + 1)[:, None]
        np.testing.assert_allclose(diagonal, expected, atol=1e-9)


def test_initial_states_are_normalised_superpositions_of_1_and_2(states):
    psi = quantum.to_complex(states)
    weight = sum(jnp.abs(jnp.sum(psi * quantum.eigenstate(n, PHYSICS.nx).astype(np.float32), axis=1)) ** 2 for n in (1, 2))
    np.testing.assert_allclose(jnp.sum(jnp.abs(psi) ** 2, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(weight, 1.0, atol=1e-5)


def test_network_matches_a_direct_convolution(task, params, states):
    state = states[0]
    (conv2, bias2), (conv1, bias1), (dense, bias) = [tuple(np.asarray(a, np.float64) for a in layer) for layer in params]
    x = np.asarray(state, np.float64)
    # Keras 'valid' convolutions written out: output i sees inputs 2i, 2i+1, 2i+2.
    first = np.tanh(np.array([np.einsum("kc,kcf->f", x[2 * i : 2 * i + 3], conv2[:, :, 0]) for i in range(15)]) + bias2)
    second = np.tanh(np.array([np.einsum("kc,kcf->f", first[2 * i : 2 * i + 3], conv1) for i in range(7)]) + bias1)
    expected = second.reshape(-1) @ dense[:, 0] + bias[0]
    with jax.default_matmul_precision("highest"):  # GPUs would otherwise multiply in TF32
        np.testing.assert_allclose(task.dynamics.policy(params, state), expected, rtol=1e-4)
        # So do lax's own convolutions, which the receptive-field matmuls stand in for.
        (conv2, bias2), (conv1, bias1), (dense, bias) = params
        image = state[None, :, :, None]
        hidden = jax.lax.conv_general_dilated(image, conv2, (2, 2), "VALID", dimension_numbers=("NHWC", "HWIO", "NHWC"))
        hidden = jnp.tanh(hidden[:, :, 0] + bias2)
        hidden = jax.lax.conv_general_dilated(hidden, conv1, (2,), "VALID", dimension_numbers=("NWC", "WIO", "NWC"))
        hidden = jnp.tanh(hidden + bias1)
        np.testing.assert_allclose((hidden.reshape(-1) @ dense + bias)[0], expected, rtol=1e-4)
    # The flagged start: output weights at zero, so the control is exactly 0.
    assert task.dynamics.policy(task.init_params(jax.random.PRNGKey(1), True), state) == 0.0


def test_loss_gradient_matches_finite_differences(params, states):
    with jax.enable_x64(True):
        task = quantum.make(quantum.Config(target=4, steps=32))
        # Glorot output scaled up: controls of order 1-10, so the loss depends on them visibly.
        params = float64(params)
        params[-1] = (100.0 * params[-1][0], params[-1][1])
        states = float64(states[:2])
        grad = jax.jit(jax.grad(lambda p: reference_loss(task.dynamics, p, states)))(params)
        grad_norm = jnp.sqrt(sum(jnp.sum(g**2) for g in jax.tree.leaves(grad)))
        assert grad_norm > 1e-2  # nonzero controls: the loss depends on the parameters
        leaves, treedef = jax.tree.flatten(params)
        keys = jax.random.split(jax.random.PRNGKey(9), len(leaves))
        random = [jax.random.normal(k, a.shape, a.dtype) for k, a in zip(keys, leaves)]
        h = 3e-6  # the step length in parameter space (directions have unit length); O(h^2) error ~1e-9

        @jax.jit  # the tree arithmetic in one program, not compiled operation by operation
        def slopes(direction):
            length = jnp.sqrt(sum(jnp.sum(d**2) for d in direction))
            direction = treedef.unflatten([d / length for d in direction])
            shifted = lambda s: jax.tree.map(lambda p, d: p + s * h * d, params, direction)
            finite_difference = (reference_loss(task.dynamics, shifted(1.0), states)
                                 - reference_loss(task.dynamics, shifted(-1.0), states)) / (2 * h)
            return finite_difference, sum(jnp.vdot(g, d) for g, d in zip(jax.tree.leaves(grad), jax.tree.leaves(direction)))

        for direction in (random, jax.tree.leaves(grad)):
            finite_difference, analytic = slopes(direction)
            # Relative to |g|, the bound of every directional derivative: a random direction
            # is nearly orthogonal to g, and relative to itself the test would measure rounding.
            assert abs(analytic - finite_difference) < 1e-6 * grad_norm
        # The engine's R flow is this same gradient.
        _, flows = jax.jit(lambda p: flow_gradients(task.dynamics, ("R",), p, states, task.plan))(params)
        for a, b in zip(jax.tree.leaves(flows), jax.tree.leaves(grad)):
            np.testing.assert_allclose(a[0], b, rtol=1e-9, atol=1e-12)


def test_long_evolution_gradient_is_finite_and_balanced(task, states):
    # For fixed controls psi_T is a unitary (as a real map: orthogonal) function of psi_0,
    # so the gradient of F = |<e_3|psi_T>|^2 w.r.t. psi_0 has norm 2 sqrt(F) after any
    # number of steps: neither exploding nor vanishing.
    target = jnp.asarray(quantum.eigenstate(3, PHYSICS.nx), jnp.float32)

    def final_fidelity(state, controls):
        final = jax.lax.scan(lambda s, u: (task.dynamics.step(s, u), None), state, controls)[0]
        return quantum.fidelity(final, target)

    controls = random_controls(jax.random.PRNGKey(11), 1, LONG, jnp.float32)[0]
    value, (grad_state, grad_controls) = jax.jit(jax.value_and_grad(final_fidelity, argnums=(0, 1)))(states[0], controls)
    assert jnp.all(jnp.isfinite(grad_state)) and jnp.all(jnp.isfinite(grad_controls))
    assert float(value) > 1e-3  # the controls moved the state towards e_3: a nonzero gradient
    np.testing.assert_allclose(jnp.linalg.norm(grad_state), 2 * jnp.sqrt(value), rtol=1e-3)


def test_all_flows_finite_over_a_long_evolution(params, states):
    task = quantum.make(quantum.Config(steps=LONG))
    loss, grads = jax.jit(lambda p, x: flow_gradients(task.dynamics, FLOWS, p, x, task.plan))(params, states[:1])
    assert 0.0 <= float(loss) <= LONG
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree.leaves(grads))


def test_loss_lies_between_zero_and_horizon(task, params, states):
    # Strong random controls: large tilts, far from any trained policy.
    params = jax.tree.map(lambda a: 20.0 * a, params)

    def per_trajectory(x0):
        trajectory = reference_rollout(task.dynamics, params, x0)
        return task.dynamics.loss(trajectory.states, trajectory.controls)

    losses = jax.jit(jax.vmap(per_trajectory))(states)
    horizon = task.dynamics.horizon
    slack = 1e-4 * horizon  # float32 rounding of the norm
    assert jnp.all(losses >= -slack) and jnp.all(losses <= horizon + slack)


def test_a_traced_target_gives_the_loss_of_that_target_built_in(task, states):
    """A sweep passes the target per cell as a traced number: each must score like its own task,
    and targets must differ (a loss that ignored the number would pass the first check)."""
    per_cell = jax.jit(lambda target, s: task.cell_option.dynamics(target).loss(s, None))
    trajectory = jnp.stack([states, jnp.roll(states, 1, axis=1)], axis=1)  # [B, 2 steps, nx, 2]
    losses = []
    for target in quantum.TARGETS:
        built_in = quantum.make(quantum.Config(target=target)).dynamics.loss
        expected = jax.vmap(lambda s: built_in(s, None))(trajectory)
        got = jax.vmap(lambda s: per_cell(jnp.int32(target), s))(trajectory)
        np.testing.assert_array_equal(got, expected)
        losses.append(got)
    assert not np.allclose(losses[0], losses[1]) and not np.allclose(losses[1], losses[2])


@pytest.mark.slow
def test_short_training_lowers_the_test_loss(task):
    config = TrainConfig(mode="C", train_size=32, test_size=32, batch=8, epochs=8)
    trainer = make_trainer(task, config)
    state = trainer.init(seed_array(config))
    # Zero control keeps every state in span{e_1, e_2}, orthogonal to the target: loss exactly T.
    untrained = float(trainer.evaluate(state.params, trainer.test_states)[0])
    np.testing.assert_allclose(untrained, task.dynamics.horizon, rtol=1e-5)
    test_losses = []
    for _ in range(config.epochs):
        state, metrics = trainer.epoch(state, trainer.batches, trainer.train_states, trainer.test_states)
        assert bool(metrics["finite"][0])
        test_losses.append(float(metrics["test_loss"][0]))
    assert all(0.0 <= loss <= task.dynamics.horizon for loss in test_losses)
    assert test_losses[-1] < 0.9 * test_losses[0]  # seen: 128.0 untrained, 127.96 -> 88.8 over the 8 epochs


@pytest.mark.parametrize("changes, option", [
    ({"target": 7}, "quantum.Config.target"),
    ({"steps": 0}, "quantum.Config.steps"),
    ({"dt": 0.0}, "quantum.Config.dt"),
    ({"dt": float("nan")}, "quantum.Config.dt"),
])
def test_config_rejects_bad_values(changes, option):
    with pytest.raises(InputError, match=option):
        quantum.Config(**changes)


def test_options_are_cli_ready():
    # scripts/train.py puts every task's options into one parser; a name that several
    # configs share (--steps, --dt) is parsed once, so its type must agree everywhere.
    parser = argparse.ArgumentParser()
    types = {f.name: f.type for f in dataclasses.fields(TrainConfig)}
    present = set(add_options(parser, TrainConfig, "training"))
    for name in sorted(set(tasks.entries()) - {"quantum"}):
        config_class = tasks.load(name).Config
        present |= set(add_options(parser, config_class, name, present))
        types.update({f.name: f.type for f in dataclasses.fields(config_class)})
    add_options(parser, quantum.Config, "quantum", present)
    for field in dataclasses.fields(quantum.Config):
        assert field.type in ("int", "float", "str", "bool") and field.metadata["help"]
        assert types.get(field.name, field.type) == field.type, f"--{field.name} has another type in another config"
    assert vars(parser.parse_args(["--target", "5", "--dt", "0.03"])) == {"target": 5, "dt": 0.03}
    assert quantum.DEFAULT_EPOCHS == 1000
