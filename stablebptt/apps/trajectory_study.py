"""The trajectory study: final-state error against a float64 reference, and the time per simulated second,
per integrator, time step and precision.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

from stablebptt.apps.measuring import (PRECISIONS, cast, compile_call, flat_states, policy_params, precision,
                                      rollout_program, run_once, time_round_robin, to_numpy)

if TYPE_CHECKING:
    from stablebptt.apps.accuracy import AccuracyConfig


CARTPOLE_DURATION, REPULSION_DURATION = 1.0, 4.0
QUANTUM_DURATION = 128 * 0.0625  # the paper's 128 steps of 0.0625


@dataclass(frozen=True)
class TrajectorySetup:
    """One task's side of the trajectory study.

    Attributes:
      task: registry name.
      label: the set-up in words (for tables and plots).
      duration: simulated time of every rollout.
      integrators: the schemes compared.
      dts: the time steps, each dividing ``duration`` into whole steps.
      paper: the paper's (integrator, dt), the baseline of the cost ratios.
      make_task: ``make_task(integrator, dt) -> Task``; call inside the precision wanted (MJX bakes it into the model).
      controls: ``controls(rng, batch)``: one fixed control per trajectory, held for the whole rollout.
      reference: ``reference(initial_states, controls) -> (final states [batch, numbers], description)`` in float64.
    """

    task: str
    label: str
    duration: float
    integrators: tuple[str, ...]
    dts: tuple[float, ...]
    paper: tuple[str, float]
    make_task: Callable
    controls: Callable
    reference: Callable


def cartpole_setup(poles: int, quick: bool) -> TrajectorySetup:
    from stablebptt.tasks import cartpole_equations, mjcf
    reference_dt = 1e-4

    def make_task(integrator, dt):
        return mjcf.make(mjcf.Config(poles=poles, integrator=integrator, dt=dt))

    def controls(rng, batch):
        return rng.uniform(-2.0, 2.0, (batch, 1))  # a constant force on the cart, in newtons

    def reference(initial_states, forces):
        import jax.numpy as jnp
        from stablebptt.integrators import rk4
        from stablebptt.scene import State
        steps = round(CARTPOLE_DURATION / reference_dt)
        with precision(64):
            arguments = (cast(initial_states, 64), cast(forces, 64))
            mjx_step = make_task("rk4", reference_dt).dynamics.step
        mjx_final = run_once(compile_call(rollout_program(mjx_step, steps), arguments, 64)[0])[0]
        # Independent check: RK4 of the closed-form rigid-body equations at the same step.
        derivative = lambda s, f: State(s.qvel, cartpole_equations.exact_accelerations(s, f[0]), jnp.zeros_like(s.act))
        closed_final = run_once(compile_call(rollout_program(rk4(derivative, reference_dt), steps), arguments, 64)[0])[0]
        mjx_final, closed_final = flat_states(mjx_final), flat_states(closed_final)
        agreement = float(abs(mjx_final - closed_final).max())
        return mjx_final, (f"float64 MJX RK4 at dt {reference_dt:g} ({steps} steps); RK4 of the closed-form "
                           f"equations at the same dt agrees to {agreement:.1e}")

    dts = (0.02, 0.01, 0.005) if quick else (0.02, 0.01, 0.005, 0.0025, 0.001)
    label = f"Cart-pole (MJX), {poles} pole{'s' if poles > 1 else ''}"
    return TrajectorySetup("cartpole", label, CARTPOLE_DURATION, ("euler", "implicitfast", "rk4"), dts, ("euler", 0.01),
                           make_task, controls, reference)


def repulsion_setup(quick: bool) -> TrajectorySetup:
    from stablebptt.tasks import repulsion

    def make_task(integrator, dt):
        return repulsion.make(repulsion.Config(integrator=integrator, steps=round(REPULSION_DURATION / dt)))

    def controls(rng, batch):
        return rng.uniform(-1.0, 1.0, (batch, 4))  # (c0, c1) per driver; c0 < 0 pulls a driver through the evaders

    def reference(initial_states, coefficients):
        finals = []
        with precision(64):
            arguments = (cast(initial_states, 64), cast(coefficients, 64))
        for steps in (7680, 15360):
            step = make_task("rk4", REPULSION_DURATION / steps).dynamics.step
            finals.append(flat_states(run_once(compile_call(rollout_program(step, steps), arguments, 64)[0])[0]))
        agreement = float(abs(finals[0] - finals[1]).max())
        return finals[1], (f"float64 RK4 with 15360 steps (dt {REPULSION_DURATION / 15360:.2g}); "
                           f"half as many steps agree to {agreement:.1e}")

    steps = (30, 60, 120) if quick else (30, 60, 120, 240, 480, 960)
    return TrajectorySetup("repulsion", "Repulsion", REPULSION_DURATION, ("euler", "rk4"),
                           tuple(REPULSION_DURATION / s for s in steps), ("euler", REPULSION_DURATION / 60),
                           make_task, controls, reference)


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


def trajectory_setups(config: AccuracyConfig) -> list[TrajectorySetup]:
    makers = {"cartpole": lambda: cartpole_setup(config.poles, config.quick),
              "repulsion": lambda: repulsion_setup(config.quick),
              "quantum": lambda: quantum_setup(config.quick)}
    return [makers[name]() for name in config.task_list]


def trajectory_study(setup: TrajectorySetup, config: AccuracyConfig, log: Callable) -> list[dict]:
    """Rows (one per integrator, dt and precision): final-state error and time per simulated second."""
    import jax
    import numpy as np
    from stablebptt.flows import flow_gradients

    rng = np.random.default_rng(config.seed)
    with precision(64):  # float64 initial states; float32 runs start from their rounding
        paper_task = setup.make_task(*setup.paper)
        initial_states = to_numpy(paper_task.sample_initial_states(jax.random.PRNGKey(config.seed), config.batch))
    controls = setup.controls(rng, config.batch)
    reference, description = setup.reference(initial_states, controls)
    log(f"{setup.task}: reference = {description}")

    forward, gradient, meta = {}, {}, {}
    params = policy_params(paper_task, config.seed)
    for integrator in setup.integrators:
        for dt in setup.dts:
            steps = round(setup.duration / dt)
            for bits in PRECISIONS:
                key = (integrator, dt, bits)
                with precision(bits):
                    task = setup.make_task(integrator, dt)
                    arguments = (cast(initial_states, bits), cast(controls, bits))
                    gradient_arguments = (cast(params, bits), cast(initial_states, bits))
                call, compile_seconds = compile_call(rollout_program(task.dynamics.step, steps), arguments, bits)
                if dt == setup.paper[1]:
                    # What a training update costs: the task's own loss, horizon and policy.
                    grad = jax.jit(lambda p, x, d=task.dynamics: flow_gradients(d, ("R",), p, x))
                    gradient[key] = compile_call(grad, gradient_arguments, bits)[0]
                final = run_once(call)[0]
                error = float(np.max(np.abs(flat_states(final) - reference)))
                forward[key] = call
                meta[key] = dict(steps=steps, error=error, compile_s=compile_seconds)
                log(f"  {integrator:14s} dt {dt:<8.4g} float{bits}: error {error:.2e}  (compiled in {compile_seconds:.1f} s)")
    forward_seconds = time_round_robin(forward, config.rounds)
    gradient_seconds = time_round_robin(gradient, max(3, config.rounds // 3))

    baseline = forward_seconds[setup.paper + (32,)]
    rows = []
    for key, seconds in forward_seconds.items():
        integrator, dt, bits = key
        rows.append({
            "task": setup.task, "setup": setup.label, "integrator": integrator, "precision": f"float{bits}", "dt": dt,
            "steps": meta[key]["steps"], "paper_dt": setup.paper[1], "simulated_time": setup.duration, "batch": config.batch,
            "error": meta[key]["error"],
            "ms_per_simulated_second": 1e3 * seconds / setup.duration,
            "ms_per_step": 1e3 * seconds / meta[key]["steps"],
            "cost_vs_paper": seconds / baseline,
            "gradient_ms_per_simulated_second": 1e3 * gradient_seconds[key] / setup.duration if key in gradient else float("nan"),
            "compile_s": meta[key]["compile_s"],
            "reference": description,
        })
    return rows
