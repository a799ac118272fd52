"""The MJCF task in the studies: its cart-poles (``--poles``), checked against closed-form equations.

The trajectory study's reference is float64 MJX RK4 at a tiny step, checked by RK4 of
the cart-pole's closed-form equations; the gradient study starts the poles hanging (the
paper) and upright (chaotic); the benchmark times each pole count, and its steps table
compares the simulators MJX offers with the closed-form equations as the floor.
"""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

from stablebptt.apps.bench import BenchCase, combined_modes, make_update, time_variants
from stablebptt.apps.gradient_study import GradientSetup
from stablebptt.apps.measuring import cast, compile_call, flat_states, precision, rollout_program, run_once
from stablebptt.apps.trajectory_study import TrajectorySetup
from stablebptt.errors import InputError
from stablebptt.tasks import mjcf_spec

if TYPE_CHECKING:
    from stablebptt.apps.accuracy import AccuracyConfig
    from stablebptt.apps.bench import BenchConfig

CARTPOLE_DURATION = 1.0


def cartpole_setup(poles: int, quick: bool) -> TrajectorySetup:
    from stablebptt.tasks import cartpole_equations, mjcf
    reference_dt = 1e-4

    def make_task(integrator, dt):
        return mjcf.make(mjcf.Config(poles=poles, integrator=integrator, dt=dt))

    def controls(rng, batch):
        return rng.uniform(-2.0, 2.0, (batch, 1))  # a constant force on the cart, in newtons

    def reference(initial_states, forces):
        import jax.numpy as jnp

        from stablebptt.physics.integrators import rk4
        from stablebptt.physics.lean_step import State
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


def trajectory_setup(config: AccuracyConfig) -> TrajectorySetup:
    return cartpole_setup(config.poles, config.quick)


def gradient_setup(config: AccuracyConfig) -> GradientSetup:
    from stablebptt.tasks import mjcf

    def upright(states):
        # Angles 0 +- 30 degrees instead of pi +- 30: the poles fall and tumble, a chaotic motion.
        qpos = states.qpos.copy()
        qpos[:, 1:] -= 3.141592653589793
        return states._replace(qpos=qpos)

    return GradientSetup("cartpole", f"cart-pole, {config.gradient_poles} poles, MJX Euler",
                         lambda: mjcf.make(mjcf.Config(poles=config.gradient_poles)), 0.01,
                         (20, 60) if config.quick else (100, 200, 300, 500, 1000, 2000, 3000),
                         {"hanging (paper)": lambda s: s, "upright": upright})


# The cart-pole simulators of the steps table: option name -> row label.
SIMULATORS = {"generated": "generated step, body by body (the default)", "stages": "MJX stages (scene analysis)",
              "autodiff": "MJX stages, autodiff through M and its solve", "dense": "MJX stages, dense mass matrix",
              "mjx": "mjx.step, MuJoCo default flags", "floor": "closed-form equations (floor)"}


def bench_cases(module, config: BenchConfig) -> list[BenchCase]:
    """One case per pole count of ``--poles``, each with the steps table of its simulators (``--simulators``)."""
    chosen = config.simulator_list or tuple(SIMULATORS)
    unknown = [name for name in chosen if name not in SIMULATORS]
    if unknown:
        raise InputError(f"--simulators takes a comma-separated subset of {', '.join(SIMULATORS)}, got {','.join(chosen)}")
    return [BenchCase(f"Cart-pole (MJX), {count} pole{'s' if count > 1 else ''}", module.Config(poles=count),
                      lambda count=count: pipeline_table(count, config.batch, config.rounds, chosen))
            for count in config.pole_list]


def pipeline_table(poles: int, batch: int, rounds: int, simulators: tuple = tuple(SIMULATORS)) -> list[str]:
    """R updates of the cart-pole through each simulator in ``simulators`` (C too for the generated step and
    the floor), with the parts of the generated step's update where it is among them."""
    import mujoco

    from stablebptt.flows.modes import MODES
    from stablebptt.physics import lean_step, scene
    from stablebptt.tasks import cartpole_equations, mjcf
    generated = mjcf.make(mjcf.Config(poles=poles))
    stages = mjcf.make(mjcf.Config(poles=poles, pipeline="stages"))
    with_step = lambda step: dataclasses.replace(stages, dynamics=dataclasses.replace(stages.dynamics, step=step))
    model = mjcf_spec.load_model(mjcf.Config(poles=poles).model_path)
    effects = scene.analyze(model)

    def dense():
        dense_model = scene.lean_model(model, effects)
        dense_model.opt.jacobian = mujoco.mjtJacobian.mjJAC_DENSE  # what lean_model replaces by the sparse path
        return with_step(lean_step.make_step(dense_model, effects, "stages"))

    build = {"generated": lambda: generated, "stages": lambda: stages,
             "autodiff": lambda: with_step(lean_step.make_step(scene.lean_model(model, effects), effects, "stages", implicit=False)),
             "dense": dense, "mjx": lambda: mjcf.make(mjcf.Config(poles=poles, pipeline="mjx")),
             "floor": lambda: with_step(cartpole_equations.make_step(0.01))}
    chosen = {name: build[name]() for name in SIMULATORS if name in simulators}
    regular = MODES[0]
    variants = {(SIMULATORS[name], regular): make_update(task, regular, batch) for name, task in chosen.items()}
    for name in ("generated", "floor"):  # the combined modes too, on the default step and the floor
        if name in chosen:
            variants.update({(SIMULATORS[name], mode): make_update(chosen[name], mode, batch) for mode in combined_modes()})
    times = time_variants(variants, rounds)
    base, lowest = (times.get((SIMULATORS[name], regular), (None,))[0] for name in ("mjx", "floor"))
    ratio = lambda ms, reference: f"{ms / reference:.2f}" if reference else ""
    lines = [f"### Cart-pole, {poles} pole{'s' if poles > 1 else ''}: where the time goes", "",
             f"| simulator | mode | ms (median) | / mjx.step default | / floor ({regular}) | compile s |",
             "|---|---|---:|---:|---:|---:|"]
    for (label, mode), (ms, compile_s) in times.items():
        lines.append(f"| {label} | {mode} | {ms:.2f} | {ratio(ms, base)} | {ratio(ms, lowest)} | {compile_s:.1f} |")
    if "generated" not in chosen:
        return lines + [""]
    return lines + [""] + parts_table(generated, poles, batch, rounds, variants[SIMULATORS["generated"], regular])


def parts_table(task, poles: int, batch: int, rounds: int, whole_update) -> list[str]:
    """The lean R update split: the rollout alone, and every step's Jacobian in one batched call.

    ``whole_update`` (the pipeline table's compiled lean R update and its
    setup, not compiled again) is timed in the same round-robin, so the rest
    by difference does not mix two tables' machine states.
    """
    import jax
    import jax.random as random

    from stablebptt.flows.gradients import reference_loss, reference_rollout
    from stablebptt.flows.linearized import step_jacobians

    dynamics = task.dynamics
    params = task.init_params(random.PRNGKey(0), False)
    starts = task.sample_initial_states(random.PRNGKey(1), batch)
    # The (state, control) pairs of one rollout, all steps and examples in one batch.
    visited = jax.jit(jax.vmap(lambda x0: reference_rollout(dynamics, params, x0)))(starts)
    merge = lambda tree: jax.tree.map(lambda a: a.reshape((a.shape[0] * a.shape[1],) + a.shape[2:]), tree)
    pairs = (merge(visited.states), merge(visited.controls))

    def jacobians(states, controls):
        return jax.tree.map(lambda a: a.sum(), step_jacobians(dynamics.step, states, controls, task.plan.known_columns))

    whole = "whole R update"
    times = time_variants({"rollout only (policy and lean step, no derivatives)": (
                               jax.jit(lambda p, x: reference_loss(dynamics, p, x)), lambda: (params, starts)),
                           f"every step's Jacobian, one batched call ({dynamics.horizon} x {batch} examples)": (
                               jax.jit(jacobians), lambda: pairs),
                           whole: whole_update}, rounds)
    whole_ms = times.pop(whole)[0]
    lines = [f"### Cart-pole, {poles} pole{'s' if poles > 1 else ''}: parts of the default R update", "",
             "| part | ms (median) | / whole R update | compile s |", "|---|---:|---:|---:|"]
    for name, (ms, compile_s) in times.items():
        lines.append(f"| {name} | {ms:.2f} | {ms / whole_ms:.2f} | {compile_s:.1f} |")
    rest = whole_ms - sum(ms for ms, _ in times.values())
    lines.append(f"| the rest, by difference (adjoint recurrence, policy Jacobians and pullback, Adam) | {rest:.2f} | "
                 f"{rest / whole_ms:.2f} | |")
    lines.append(f"| whole R update (timed with the parts) | {whole_ms:.2f} | 1.00 | |")
    return lines + [""]
