"""The quantum task in the studies: the exact solution under a constant control as the reference."""
from __future__ import annotations

from typing import TYPE_CHECKING

from stablebptt.apps.gradient_study import GradientSetup
from stablebptt.apps.trajectory_study import TrajectorySetup

if TYPE_CHECKING:
    from stablebptt.apps.accuracy import AccuracyConfig

QUANTUM_DURATION = 128 * 0.0625  # the paper's 128 steps of 0.0625


def quantum_setup(quick: bool) -> TrajectorySetup:
    from stablebptt.tasks import quantum
    physics = quantum.Physics()

    def make_task(integrator, dt):
        del integrator  # Crank-Nicolson is the task's only scheme
        return quantum.make(quantum.Config(dt=dt, steps=round(QUANTUM_DURATION / dt)))

    def controls(rng, batch):
        return rng.uniform(-5.0, 5.0, batch)  # tilts comparable to the level spacing

    def reference(initial_states, tilts):
        import numpy as np
        # A constant control makes H constant: psi(T) = V exp(-i Lambda T) V^T psi(0), exactly (float64 LAPACK).
        n, dx = physics.nx, physics.dx
        laplacian = (np.diag(np.full(n, -2.0)) + np.diag(np.ones(n - 1), 1) + np.diag(np.ones(n - 1), -1)) / dx**2
        psi0 = initial_states[..., 0] + 1j * initial_states[..., 1]
        finals = []
        for psi, u in zip(psi0, tilts):
            energies, vectors = np.linalg.eigh(-laplacian + u * np.diag(physics.grid))
            psi_t = vectors @ (np.exp(-1j * energies * QUANTUM_DURATION) * (vectors.T @ psi))
            finals.append(np.stack([psi_t.real, psi_t.imag], axis=-1).reshape(-1))
        return np.array(finals), "exact solution of the semi-discrete equation (eigenvectors of H, float64)"

    steps = (32, 128, 512) if quick else (32, 64, 128, 256, 512, 1024, 2048)
    return TrajectorySetup("quantum", "Quantum", QUANTUM_DURATION, ("crank-nicolson",),
                           tuple(QUANTUM_DURATION / s for s in steps), ("crank-nicolson", 0.0625),
                           make_task, controls, reference)


def trajectory_setup(config: AccuracyConfig) -> TrajectorySetup:
    return quantum_setup(config.quick)


def gradient_setup(config: AccuracyConfig) -> GradientSetup:
    from stablebptt.tasks import quantum
    return GradientSetup("quantum", "quantum, Crank-Nicolson", lambda: quantum.make(quantum.Config()), 0.0625,
                         (20, 60) if config.quick else (100, 300, 1000), {"paper": lambda s: s})
