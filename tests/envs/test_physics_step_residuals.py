"""Each physics step recomputed in reverse mode's backward pass rather than its intermediates stored
(``env_task(physics_steps_recomputed=...)``, ``--physics-step-residuals``): the same values and the same
derivative (the closed form of semi-implicit Euler), a program that rematerializes each ``mjx.step`` and
stores fewer of its intermediates; chosen by default where a control step's derivative spans several
physics steps; bad values refused in one line, and so is the choice on an env whose step does not call
``mjx.step`` through MJX's package, where it would change nothing."""
import contextlib
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stablebptt.envs.adapter import env_task
from stablebptt.envs.derivative_model import steps_traced
from stablebptt.envs.protocol import EnvError
from stablebptt.physics import constraint_derivatives

from conftest import refused_in_one_line
from envs_for_tests import Ball, BoundStepBall, SubsteppedBall

RECOMPUTED = "each physics step recomputed in the backward pass"


def test_by_default_recomputed_where_a_control_step_spans_several_physics_steps():
    assert RECOMPUTED in env_task(SubsteppedBall(), horizon=2, diagnose=False).summary
    for substeps in (2, 10):  # the derivative through 2 of the env's 10, or through its own 10
        assert RECOMPUTED in env_task(SubsteppedBall(), horizon=2, diagnose=False, gradient_substeps=substeps).summary
    assert RECOMPUTED not in env_task(SubsteppedBall(), horizon=2, diagnose=False, gradient_substeps=1).summary
    assert RECOMPUTED not in env_task(Ball(), horizon=2, diagnose=False).summary  # one physics step a control step
    assert RECOMPUTED in env_task(Ball(), horizon=2, diagnose=False, physics_steps_recomputed=True).summary
    assert RECOMPUTED not in env_task(SubsteppedBall(), horizon=2, diagnose=False,
                                      physics_steps_recomputed=False).summary


def _windows(env, qpos: float) -> dict:
    """The position ``env`` reaches from ``qpos`` in two control steps of one action, as a function of the action,
    traced by ``env``'s task with each physics step stored (False) and recomputed (True)."""
    state = env.reset(jax.random.PRNGKey(0))
    state = state._replace(data={**state.data, "qpos": jnp.array([qpos])})

    def window(task):
        def position_after(action):
            return task.dynamics.step(task.dynamics.step(state, action), action).data["qpos"][0]
        return position_after
    return {recomputed: window(env_task(env, horizon=2, diagnose=False, physics_steps_recomputed=recomputed))
            for recomputed in (False, True)}


def test_recomputed_steps_keep_values_and_derivative_and_store_fewer_intermediates():
    env = SubsteppedBall()  # 10 physics steps of 2 ms per control step
    windows = _windows(env, 0.05)  # 15 cm clear: no contact
    action = jnp.array([0.3])
    programs = {recomputed: jax.jit(jax.value_and_grad(window)) for recomputed, window in windows.items()}
    (stored_value, stored_slope), (recomputed_value, recomputed_slope) = (programs[False](action),
                                                                          programs[True](action))
    assert float(stored_value) == float(recomputed_value)
    # Semi-implicit Euler, n steps of h under a constant force: d position / d action = (gear / mass) h^2 n (n + 1) / 2,
    # here n the two control steps' physics steps.
    gear, mass = float(env._mjx_model.actuator_gear[0, 0]), float(env._mjx_model.body_mass[1])
    n, h = 2 * env.n_substeps, env._sim_dt
    np.testing.assert_allclose(float(recomputed_slope[0]), gear / mass * h ** 2 * n * (n + 1) / 2, rtol=1e-5)
    np.testing.assert_allclose(float(recomputed_slope[0]), float(stored_slope[0]), rtol=1e-6)
    # Rematerialized: the backward pass runs each mjx.step again (JAX's remat), and the loops stack fewer of
    # its intermediates.
    jaxprs = {recomputed: str(jax.make_jaxpr(jax.grad(window))(action)) for recomputed, window in windows.items()}
    assert "remat" in jaxprs[True] and "remat" not in jaxprs[False]
    stores = {recomputed: program.lower(action).as_text().count("stablehlo.dynamic_update_slice")
              for recomputed, program in programs.items()}
    assert stores[True] < stores[False], stores


def test_a_recomputed_step_keeps_the_solvers_solution_and_runs_none_of_its_iterations_again():
    windows = _windows(SubsteppedBall(), -0.102)  # pressed 2 mm into the plane
    action = jnp.array([-0.5])
    programs = {recomputed: jax.jit(jax.value_and_grad(window)) for recomputed, window in windows.items()}
    (stored_value, stored_slope), (recomputed_value, recomputed_slope) = programs[False](action), programs[True](action)
    assert float(stored_value) == float(recomputed_value)
    assert 0 < abs(float(stored_slope[0])) < 1e-3  # the contact holds the ball: below the free 4.2e-3
    np.testing.assert_allclose(float(recomputed_slope[0]), float(stored_slope[0]), rtol=1e-5)
    # The solver's loops (its iterations, their line searches) run in the forward pass alone: the backward
    # pass, which runs each physics step again, holds fewer loops than the stored program's (7 against 8;
    # with the solver run again there, 11).
    loops = {recomputed: program.lower(action).as_text().count("stablehlo.while")
             for recomputed, program in programs.items()}
    assert loops[True] < loops[False], loops


def _ops_run_again(text: str) -> int:
    """The ops of a lowered program (its text with debug info) that a rematerialised computation holds: those
    whose location is, or calls from, one JAX names ``rematted_computation``."""
    places = dict(re.findall(r"^(#loc\d+) = (.*)$", text, re.M))
    again = {alias for alias, where in places.items() if "rematted_computation" in where}
    while True:  # a call site or fused location that holds one of them lies in it too
        more = {alias for alias, where in places.items()
                if alias not in again and any(held in again for held in re.findall(r"#loc\d+", where))}
        if not more:
            break
        again |= more
    at = re.compile(r"loc\((#loc\d+)\)\s*$")
    return sum(1 for line in text.splitlines()
               if not line.startswith("#loc") and (found := at.search(line)) and found.group(1) in again)


def test_a_recomputed_step_keeps_the_values_of_mjxs_functions_this_package_differentiates(monkeypatch):
    # Their tangents read their values and inputs (physics/values_kept.py): the backward pass keeps the body
    # frames, inertias, the mass matrix's factor and solves rather than running MJX's functions again.
    action = jnp.array([-0.5])

    def run_again() -> tuple[int, float]:
        """The ops the backward pass runs again, as lowered, and the slope (a new env: its step traced anew)."""
        window = _windows(SubsteppedBall(), -0.102)[True]  # in contact: every stage of the step runs
        program = jax.jit(jax.grad(window))
        return _ops_run_again(program.lower(action).as_text(debug_info=True)), float(program(action)[0])
    kept_ops, kept_slope = run_again()
    # The policy is read at each trace (constraint_derivatives._step_as_chosen): the solver's solution alone.
    monkeypatch.setattr(constraint_derivatives, "_KEPT_ACROSS_RECOMPUTE", (constraint_derivatives.SOLVER_SOLUTION,))
    solution_only_ops, solution_only_slope = run_again()
    assert kept_ops < 0.6 * solution_only_ops, (kept_ops, solution_only_ops)  # 2,320 against 5,534 as written
    np.testing.assert_allclose(kept_slope, solution_only_slope, rtol=1e-6)


def test_bad_values_are_refused_in_one_line(tmp_path, capsys):
    with pytest.raises(EnvError, match="env_task's physics_steps_recomputed must be True, False or None"):
        env_task(SubsteppedBall(), horizon=2, diagnose=False, physics_steps_recomputed="yes")
    refused_in_one_line(capsys, tmp_path / "refused", "--physics-step-residuals", "--env",
                        "envs_for_tests:make_substepped_ball", "--physics-step-residuals", "kept", "--epochs", "1")


def test_asked_of_a_step_that_binds_its_own_mjx_step_it_is_refused_in_one_line(tmp_path, capsys):
    env = BoundStepBall()
    state, action = env.reset(jax.random.PRNGKey(0)), jnp.array([0.3])
    with pytest.raises(EnvError, match="calls no mujoco.mjx.step through MJX's package"):
        env_task(env, horizon=2, diagnose=False, physics_steps_recomputed=True).dynamics.step(state, action)
    # The default leaves that env's intermediates stored without a word against it: its step traces.
    assert jnp.isfinite(env_task(env, horizon=2, diagnose=False).dynamics.step(state, action).reward)
    refused_in_one_line(capsys, tmp_path / "refused", "calls no mujoco.mjx.step", "--env",
                        "envs_for_tests:make_bound_step_ball", "--physics-step-residuals", "recomputed",
                        "--epochs", "1")


class JittedStepBall(SubsteppedBall):
    """The substepped ball whose step the env jits itself: traced again, JAX answers from its cache."""

    def __init__(self):
        super().__init__()
        self.step = jax.jit(super().step)


def test_asked_of_a_step_the_env_jits_itself_later_traces_from_jaxs_cache_are_not_refused():
    env = JittedStepBall()
    env_step = steps_traced(False, True, True, contextlib.nullcontext, "ball")(env)  # as env_task traces it
    state, action = env.reset(jax.random.PRNGKey(0)), jnp.array([0.3])
    # Each trace through a function of its own, so that JAX traces env_step anew (it keeps a function's traces).
    first = str(jax.make_jaxpr(lambda *given: env_step(*given))(state, action))  # the env's jit traces mjx.step
    again = str(jax.make_jaxpr(lambda *given: env_step(*given))(state, action))  # its jit answers from the cache
    assert "remat" in first and again == first
    with pytest.raises(EnvError, match="calls no mujoco.mjx.step"):  # a step that never recomputes: refused
        jax.make_jaxpr(steps_traced(False, True, True, contextlib.nullcontext, "ball")(BoundStepBall()))(state, action)
