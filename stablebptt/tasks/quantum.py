"""Quantum control: steer a particle in a 1-D box into an excited eigenstate.

Schroedinger equation on [0, 2] with Dirichlet walls, discretised on ``nx``
interior points, ``H = -d^2/dx^2 + u(t) x``: the control ``u`` tilts the box.
Crank-Nicolson time stepping (unitary, so the norm is kept), each step solved
with a tridiagonal solver: O(nx) per state, batched by vmap. The state is a
real array [nx, 2] holding (re, im), so float32/float64 follow
``jax_enable_x64`` and the gradient-flow machinery sees plain real leaves.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np

from stablebptt.engine.task import CellOption, Task
from stablebptt.errors import InputError, check_field_types, config_field, keywords_named
from stablebptt.flows.dynamics import Dynamics, Plan
from stablebptt.networks import glorot_uniform

DEFAULT_EPOCHS = 1000
TARGETS = (3, 4, 5)
FILTERS = 60  # width of both convolution layers


@keywords_named
@dataclass(frozen=True)
class Config:
    """Options of the quantum-control task."""

    target: int = field(default=3, metadata={"help": "eigenstate to steer into (the paper: 3, 4 and 5)", "choices": TARGETS})
    steps: int = field(default=128, metadata={"help": "Crank-Nicolson steps, the horizon T (the paper: 128)"})
    dt: float = field(default=0.0625, metadata={"help": "Crank-Nicolson time step (the paper: 0.0625)"})

    def __post_init__(self):
        check_field_types(self)
        if self.target not in TARGETS:
            raise InputError(f"{config_field(self, 'target')} must be one of {', '.join(map(str, TARGETS))} (the eigenstate to reach), got {self.target}")
        if self.steps <= 0:
            raise InputError(f"{config_field(self, 'steps')} must be a positive integer, got {self.steps}")
        if not (math.isfinite(self.dt) and self.dt > 0):
            raise InputError(f"{config_field(self, 'dt')} must be a positive number, got {self.dt}")


@dataclass(frozen=True)
class Physics:
    """The box of the paper's public code: [0, length] with nx interior points."""

    nx: int = 32
    length: float = 2.0

    @property
    def dx(self) -> float:
        return self.length / (self.nx + 1)

    @property
    def grid(self) -> np.ndarray:
        """Positions of the interior points, x_k = k dx for k = 1..nx (float64 NumPy)."""
        return self.dx * np.arange(1, self.nx + 1)


def eigenstate(n: int, nx: int) -> np.ndarray:
    """The n-th eigenstate of the discrete Dirichlet Laplacian, sin(pi n k / (nx + 1)), normalised.

    Args:
      n: quantum number, 1 for the ground state.
      nx: number of interior grid points.

    Returns:
      A float64 NumPy vector of length ``nx`` with unit Euclidean norm.
    """
    wave = np.sin(np.pi * n * np.arange(1, nx + 1) / (nx + 1))
    return wave / np.linalg.norm(wave)


def to_complex(state: jax.Array) -> jax.Array:
    """[..., nx, 2] (re, im) -> complex [..., nx] of the matching precision."""
    return jax.lax.complex(state[..., 0], state[..., 1])


def to_real(psi: jax.Array) -> jax.Array:
    """complex [..., nx] -> real [..., nx, 2] (re, im)."""
    return jnp.stack([psi.real, psi.imag], axis=-1)


def _solve_columns(diagonal: jax.Array, off: jax.Array, columns: jax.Array) -> jax.Array:
    """Solve tridiag(off, diagonal, off) X = columns; diagonals [..., m], columns [..., m, k]."""
    lower = jnp.concatenate([jnp.zeros_like(off[..., :1]), off[..., :-1]], axis=-1)  # lower[0] lies outside
    upper = off.at[..., -1].set(0)  # and so does upper[-1]
    return jax.lax.linalg.tridiagonal_solve(lower, diagonal, upper, columns)


@jax.custom_batching.custom_vmap
def _solve_stack(diagonal: jax.Array, off: jax.Array, rhs: jax.Array) -> jax.Array:
    """Solve tridiag(off, diagonal, off) x = rhs for a stack of systems; every operand [..., m]."""
    return _solve_columns(diagonal, off, rhs[..., None])[..., 0]


@_solve_stack.def_vmap
def _solve_stack_vmap(axis_size, in_batched, diagonal, off, rhs):
    # A batched rhs against unbatched diagonals: the gradient flows' adjoint copies,
    # which share one forward pass. A CPU (LAPACK) factorizes each system once for
    # all right-hand-side columns; the GPU solver runs columns far slower than a
    # batch of systems, so there every operand gets the batch axis.
    operands = [a if batched else jnp.broadcast_to(a, (axis_size,) + a.shape)
                for a, batched in zip((diagonal, off, rhs), in_batched)]
    if in_batched[0] or in_batched[1] or not in_batched[2]:
        return _solve_stack(*operands), True

    as_columns = lambda diagonal, off, rhs: jnp.moveaxis(_solve_columns(diagonal, off, jnp.moveaxis(rhs, 0, -1)), -1, 0)
    return jax.lax.platform_dependent(diagonal, off, rhs, cpu=as_columns,
                                      default=lambda *_: _solve_stack(*operands)), True


@jax.custom_vjp
def symmetric_tridiagonal_solve(diagonal: jax.Array, off: jax.Array, rhs: jax.Array) -> jax.Array:
    """x with A x = rhs for the complex-symmetric tridiagonal A = tridiag(off, diagonal, off).

    Args:
      diagonal: A[k, k], shape [m].
      off: A[k, k+1] = A[k+1, k] in entries 0..m-2; the last entry is ignored.
      rhs: right-hand side, shape [m].

    Returns:
      The solution, shape [m]. O(m) work; vmap gives a batch of systems, also
      in the reverse pass (on a CPU, copies that share the matrix become
      right-hand-side columns of one system).
    """
    return _solve_stack(diagonal, off, rhs)


def _solve_fwd(diagonal, off, rhs):
    x = _solve_stack(diagonal, off, rhs)
    return x, (diagonal, off, x)


def _solve_bwd(residuals, x_bar):
    diagonal, off, x = residuals
    # A^T = A: the adjoint system is the forward one; dA x pulls back to -rhs_bar * x.
    rhs_bar = _solve_stack(diagonal, off, x_bar)
    off_bar = -(rhs_bar[..., :-1] * x[..., 1:] + rhs_bar[..., 1:] * x[..., :-1])
    off_bar = jnp.concatenate([off_bar, jnp.zeros_like(off_bar[..., :1])], axis=-1)
    return -rhs_bar * x, off_bar, rhs_bar


symmetric_tridiagonal_solve.defvjp(_solve_fwd, _solve_bwd)


def make_step(physics: Physics, dt: float):
    """``step(state, control)``: one Crank-Nicolson step with the control held over it.

    Solves (I + i dt/2 H) psi_{n+1} = (I - i dt/2 H) psi_n with
    H = -D2 + u x, D2 the three-point Laplacian with zero walls.

    Args:
      physics: grid of the box.
      dt: time step.

    Returns:
      A function of a real state [nx, 2] and a scalar control, returning the next state.
    """
    nx, dx = physics.nx, physics.dx
    grid = physics.grid  # NumPy: a jnp constant built here would fix its dtype before x64 is chosen
    kinetic = 1.0 / dx**2

    def step(state, control):
        psi = to_complex(state)
        potential = control * jnp.asarray(grid, state.dtype)
        walled = jnp.pad(psi, 1)  # Dirichlet: psi = 0 on both walls
        h_psi = kinetic * (2.0 * psi - walled[:-2] - walled[2:]) + potential * psi
        rhs = psi - 0.5j * dt * h_psi
        # I + i dt/2 H: the diagonal moves with the control, the off-diagonals do not.
        diagonal = 1.0 + 0.5j * dt * (2.0 * kinetic + potential)
        off = jnp.full(nx, -0.5j * dt * kinetic, psi.dtype)
        return to_real(symmetric_tridiagonal_solve(diagonal, off, rhs))

    return step


def network_init(key: jax.Array, physics: Physics, zero_output: bool = True) -> list[tuple[jax.Array, jax.Array]]:
    """Parameters of Conv2D(3 x 2, stride 2) -> Conv1D(3, stride 2) -> Dense(1).

    Glorot-uniform kernels with the Keras fans of a convolution (receptive
    field times channels), zero biases. The original's zero-init flag zeroes its
    last weight array, which with a dense bias is that (already zero) bias: its
    quantum runs start from a Glorot output layer, i.e. ``zero_output=False``.

    Args:
      key: PRNG key.
      physics: the grid, whose size fixes the input width of the dense layer.
      zero_output: start the dense layer's weights at zero (initial control exactly 0).

    Returns:
      ``[(k2, b2), (k1, b1), (w, b)]`` with k2 [3, 2, 1, F] (HWIO), k1 [3, F, F] (WIO), w [positions * F, 1].
    """
    filters = FILTERS
    k_conv2, k_conv1, k_dense = jax.random.split(key, 3)
    conv2 = glorot_uniform(k_conv2, 3 * 2 * 1, 3 * 2 * filters, (3, 2, 1, filters))
    conv1 = glorot_uniform(k_conv1, 3 * filters, 3 * filters, (3, filters, filters))
    flat = _conv_out(_conv_out(physics.nx)) * filters
    dense = jnp.zeros((flat, 1)) if zero_output else glorot_uniform(k_dense, flat, 1)
    return [(conv2, jnp.zeros((filters,))), (conv1, jnp.zeros((filters,))), (dense, jnp.zeros((1,)))]


def _conv_out(length: int, kernel: int = 3, stride: int = 2) -> int:
    """Output length of a 'valid' convolution."""
    return (length - kernel) // stride + 1


def _receptive_fields(x: jax.Array, kernel: int = 3, stride: int = 2) -> jax.Array:
    """[length, channels] -> [positions, kernel, channels]: the inputs each 'valid' output sees."""
    count = _conv_out(x.shape[0], kernel, stride)
    return jnp.stack([x[k : k + stride * (count - 1) + 1 : stride] for k in range(kernel)], axis=1)


def network_apply(params: list[tuple[jax.Array, jax.Array]], state: jax.Array) -> jax.Array:
    """The scalar control u for one state [nx, 2].

    Each convolution is one matrix product over its receptive fields: the same
    numbers as ``lax.conv_general_dilated`` with 'valid' padding (the tests check
    this), but several times faster to differentiate on CPU, where XLA's
    convolution gradients are slow at these sizes.
    """
    (conv2, bias2), (conv1, bias1), (dense, bias) = params
    # The 3 x 2 kernel spans the whole (re, im) axis: a 1-D convolution over space with 2 channels.
    fields = _receptive_fields(state)  # [15, 3, 2]
    hidden = jnp.tanh(fields.reshape(fields.shape[0], -1) @ conv2.reshape(-1, FILTERS) + bias2)
    fields = _receptive_fields(hidden)  # [7, 3, FILTERS]
    hidden = jnp.tanh(fields.reshape(fields.shape[0], -1) @ conv1.reshape(-1, FILTERS) + bias1)
    return (hidden.reshape(-1) @ dense + bias)[0]


def fidelity(states: jax.Array, target: jax.Array) -> jax.Array:
    """|<target|psi>|^2 for states [..., nx, 2] and a real target [nx]."""
    # A product and a sum, not a matmul: GPUs run float32 matmuls in TF32 by default,
    # whose 1e-3 rounding would push the loss outside [0, T].
    overlap = jnp.sum(states * target[:, None], axis=-2)  # (re, im) of the overlap
    return jnp.sum(overlap**2, axis=-1)


def sample_initial_states(physics: Physics, key: jax.Array, count: int) -> jax.Array:
    """Random superpositions of eigenstates 1 and 2: normal amplitudes, uniform phases, normalised.

    Returns:
      Real array [count, nx, 2] in the default float precision.
    """
    k_amplitude, k_phase = jax.random.split(key)
    amplitude = jax.random.normal(k_amplitude, (count, 2))
    phase = jax.random.uniform(k_phase, (count, 2), minval=0.0, maxval=2 * jnp.pi)
    amplitude = amplitude / jnp.linalg.norm(amplitude, axis=1, keepdims=True)
    basis = jnp.asarray(np.stack([eigenstate(1, physics.nx), eigenstate(2, physics.nx)]), amplitude.dtype)
    coefficients = amplitude * jnp.exp(1j * phase)
    # Broadcast and sum rather than a matmul, which a GPU may round to TF32 (norm off by 1e-3).
    return to_real(jnp.sum(coefficients[:, :, None] * basis, axis=1))


def make(config: Config, physics: Physics = Physics()) -> Task:
    """The quantum-control task: CN simulator, CNN controller, continuous fidelity loss."""
    step = make_step(physics, config.dt)
    # Row n is eigenstate n (row 0 unused), so a traced target number picks its row.
    targets = np.stack([np.zeros(physics.nx)] + [eigenstate(n, physics.nx) for n in range(1, max(TARGETS) + 1)])

    # The batched pullback repeats the convolutions' forward pass: on a CPU that costs
    # more than it saves, on a GPU it pays (docs/performance.md).
    policy_gradient = "per-step" if jax.default_backend() == "cpu" else "batched"

    def dynamics_with(target):
        """The target enters only the loss, so a sweep passes it per cell as a traced value."""
        def loss(states, controls):
            # Sum over t = 1..T of 1 - |<target|psi_t>|^2: in [0, T] while the norm is 1.
            del controls
            return jnp.sum(1.0 - fidelity(states, jnp.asarray(targets, states.dtype)[target]))

        return Dynamics(step=step, policy=network_apply, loss=loss, horizon=config.steps)

    return Task(
        name="quantum",
        dynamics=dynamics_with(config.target),
        init_params=lambda key, zero_output: network_init(key, physics, zero_output),
        sample_initial_states=lambda key, count: sample_initial_states(physics, key, count),
        cell_option=CellOption("target", dynamics_with),
        plan=Plan(policy_gradient=policy_gradient),
    )


def program_inputs(config: Config) -> dict:
    """What the task's compiled programs read besides the library and ``config``: nothing."""
    return {}
