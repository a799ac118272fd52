"""The contact study: suite models with contacts against MuJoCo's C step, per constraint-solver setting.

Trajectory error against the C step with the model's own settings, step-Jacobian error against central
differences of the C step, and the time of batched MJX rollouts and step Jacobians.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Callable

from stablebptt.apps.measuring import compile_call, precision, time_round_robin

if TYPE_CHECKING:
    import numpy as np

    from stablebptt.apps.accuracy import AccuracyConfig



CONTACT_STEPS = 50  # steps of each compared trajectory
CONTACT_SETTLE = 0.5  # seconds of MuJoCo simulation under random controls before the comparison starts
FINITE_DIFFERENCE_STEP = 1e-6


def contact_settings(model) -> list[tuple[str, int | None, float]]:
    """(label, fixed Newton iterations or None for the model's own solver, time step) of the contact study."""
    dt = float(model.opt.timestep)
    own = f"own ({int(model.opt.iterations)} it., tol {float(model.opt.tolerance):g})"
    return [(own, None, dt), ("1 iteration", 1, dt), ("2 iterations", 2, dt), ("4 iterations", 4, dt),
            (f"{own}, 2 dt", None, 2 * dt)]


def _c_rollout(model, qpos, qvel, controls) -> "np.ndarray":
    """[steps, nq + nv] states of MuJoCo's C step from (qpos, qvel) under ``controls`` [steps, nu]."""
    import mujoco
    import numpy as np
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = qpos, qvel
    visited = []
    for control in controls:
        data.ctrl[:] = control
        mujoco.mj_step(model, data)
        visited.append(np.concatenate([data.qpos, data.qvel]))
    return np.array(visited)


def _c_jacobian(model, qpos, qvel, control) -> "np.ndarray":
    """d (qpos, qvel)_next / d (qpos, qvel, ctrl) of one C step, by central differences (qpos in coordinates)."""
    import numpy as np
    point = np.concatenate([qpos, qvel, control])
    nq, nv = model.nq, model.nv

    def next_state(x):
        return _c_rollout(model, x[:nq], x[nq:nq + nv], x[None, nq + nv:])[0]

    columns = []
    for k in range(point.size):
        shift = np.zeros_like(point)
        shift[k] = FINITE_DIFFERENCE_STEP
        columns.append((next_state(point + shift) - next_state(point - shift)) / (2 * FINITE_DIFFERENCE_STEP))
    return np.stack(columns, axis=1)


def contact_study(config: AccuracyConfig, log: Callable, done: list[dict] = (),
                  on_row: Callable[[list[dict]], None] = lambda rows: None) -> list[dict]:
    """Rows per suite model with contacts and solver setting: trajectory error against MuJoCo's C step with the
    model's own settings, step-Jacobian error against central differences of the C step, and the time of a
    batched MJX rollout and of batched forward-mode step Jacobians.

    Rows in ``done`` (an earlier, interrupted call's) are kept and not measured again; ``on_row`` gets
    all rows after each new one, so a long study can be stopped and resumed."""
    from pathlib import Path

    import jax
    import jax.numpy as jnp
    import mujoco
    import numpy as np

    from stablebptt.flows.linearized import step_jacobians
    from stablebptt.physics import lean_step, scene
    from stablebptt.tasks.mjcf_spec import load_model

    rows = list(done)
    measured = {(row["model"], row["setting"]) for row in rows}
    steps = 10 if config.quick else CONTACT_STEPS
    for name in [n for n in config.contact_models.split(",") if n]:
        model = load_model(Path(config.suite) / f"{name}.xml")
        effects = scene.analyze(model)
        rng = np.random.default_rng(config.seed)
        low, high = model.actuator_ctrlrange[:, 0], model.actuator_ctrlrange[:, 1]
        random_controls = lambda count: rng.uniform(low, high, (count, model.nu))
        # A state the model reaches, with its contacts, under random controls (the model's own settings).
        settled = _c_rollout(model, model.qpos0, np.zeros(model.nv), random_controls(round(CONTACT_SETTLE / model.opt.timestep)))
        qpos, qvel = settled[-1, :model.nq], settled[-1, model.nq:]
        data = mujoco.MjData(model)
        data.qpos[:], data.qvel[:] = qpos, qvel
        mujoco.mj_forward(model, data)
        contacts = int(data.ncon)
        held = np.repeat(random_controls(steps), 2, axis=0)  # each control held for two steps: 2 dt sees the same
        truth = _c_rollout(model, qpos, qvel, held)[-1]  # the file's own settings, at the end of every setting's rollout
        truth_jacobians = {}  # time step -> central differences of the C step with the file's solver
        for label, iterations, dt in contact_settings(model):
            if (name, label) in measured:
                continue
            factor = round(dt / float(model.opt.timestep))
            controls = held[::factor][:2 * steps // factor]
            if dt not in truth_jacobians:
                truth_jacobians[dt] = _c_jacobian(scene.with_options(model, timestep=dt), qpos, qvel, controls[0])
            truth_jacobian = truth_jacobians[dt]
            with precision(64):
                lean = scene.lean_model(model, effects, timestep=dt, solver_iterations=iterations)
                step = lean_step.make_step(lean, effects)
                start = lean_step.State(jnp.asarray(qpos), jnp.asarray(qvel), jnp.zeros(model.na))
                rollout = jax.jit(lambda s, us: jax.lax.scan(lambda x, u: (step(x, u), None), s, us)[0])
                final = rollout(start, jnp.asarray(controls))
                error = float(np.max(np.abs(np.concatenate([final.qpos, final.qvel]) - truth)))
                jacobian = jax.jit(lambda s, u: step_jacobians(step, s, u))(
                    jax.tree.map(lambda a: a[None], start), jnp.asarray(controls[:1]))
                ours = np.concatenate([jacobian[0][0], jacobian[1][0]], axis=1)[:model.nq + model.nv]
                ours = np.delete(ours, np.arange(model.nq + model.nv, ours.shape[1] - model.nu), axis=1)
                jacobian_error = float(np.linalg.norm(ours - truth_jacobian) / np.linalg.norm(truth_jacobian))
            with precision(32):  # what training runs: float32, a batch of states
                lean32 = scene.lean_model(model, effects, timestep=dt, solver_iterations=iterations)
                step32 = lean_step.make_step(lean32, effects)
                batch = jax.tree.map(lambda a: jnp.broadcast_to(jnp.asarray(a, jnp.float32), (config.batch,) + np.shape(a)),
                                     lean_step.State(qpos, qvel, np.zeros(model.na)))
                batch_controls = jnp.asarray(np.broadcast_to(controls[:, None], (len(controls), config.batch, model.nu)), jnp.float32)
            forward, _ = compile_call(jax.jit(lambda s, us: jax.lax.scan(lambda x, u: (jax.vmap(step32)(x, u), None), s, us)[0]),
                                      (batch, batch_controls), 32)
            jacobians, _ = compile_call(jax.jit(lambda s, u: step_jacobians(step32, s, u)), (batch, batch_controls[0]), 32)
            seconds = time_round_robin({"forward": forward, "jacobians": jacobians}, max(2, config.rounds // 4))
            simulated = len(controls) * dt
            rows.append({"model": name, "setting": label, "iterations": iterations or 0, "dt": dt, "steps": len(controls),
                         "contacts": contacts, "trajectory_error": error, "jacobian_error": jacobian_error,
                         "ms_per_simulated_second": 1e3 * seconds["forward"] / simulated,
                         "jacobian_ms_per_step": 1e3 * seconds["jacobians"], "batch": config.batch})
            on_row(rows)
            log(f"  {name:12s} {label:32s} trajectory {error:.2e}  Jacobian {jacobian_error:.2e}  "
                f"{rows[-1]['ms_per_simulated_second']:.1f} ms / sim. s  {rows[-1]['jacobian_ms_per_step']:.1f} ms / Jacobians")
    return rows
