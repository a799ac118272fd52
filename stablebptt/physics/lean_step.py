"""The lean, differentiable MJX step: only the pipeline stages a scene needs, over (qpos, qvel, act).

``make_step(lean, effects)`` generates the step body by body where it applies
(``stablebptt.physics.rigid_body``; a scene's contacts, limits and friction loss then come from
MJX's own stages, fed the generated terms), else runs MJX's stages the scene analysis
(``stablebptt.physics.scene``) calls for - skipping camera and light poses, sensors,
tendons, collision and constraint assembly where no flag reaches them - and
differentiates through inverse dynamics where the mass-matrix solve is exact.
The constraint solver's implicit derivative is ``stablebptt.physics.constraint_derivatives``.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Callable, NamedTuple

import jax
import jax.numpy as jnp
import mujoco

from stablebptt.physics import rigid_body
from stablebptt.physics.constraint_derivatives import solve_implicitly, traced_differentiably
from stablebptt.physics.mjx_internals import collision_driver, constraint, mjx, passive, smooth
from stablebptt.physics.mjx_internals import forward as mjx_forward
from stablebptt.physics.mjx_internals import types as mjx_types
from stablebptt.physics.mjx_support import put_model

if TYPE_CHECKING:
    from stablebptt.physics.effects import SceneEffects

_DISABLE = mujoco.mjtDisableBit


class State(NamedTuple):
    """The minimal MJX state a rollout carries."""

    qpos: jax.Array
    qvel: jax.Array
    act: jax.Array


def _lean_forward(model: mjx.Model, data: mjx.Data, effects: SceneEffects, mass: bool = True) -> mjx.Data:
    """mjx.forward without the stages the scene cannot need.

    With ``mass=False`` it stops before the mass matrix and the solve and
    computes inverse dynamics instead: ``qfrc_bias`` becomes
    M(qpos) qacc + c(qpos, qvel) for the ``qacc`` that ``data`` carries
    (armature excluded: constant, it has no derivative).
    """
    data = smooth.kinematics(model, data)
    data = smooth.com_pos(model, data)
    if effects.tendons:
        data = smooth.tendon(model, data)
    if mass:
        data = smooth.crb(model, data)
        if effects.tendons:
            data = smooth.tendon_armature(model, data)
        data = smooth.factor_m(model, data)
    if effects.constraints:
        data = collision_driver.collision(model, data)
        data = constraint.make_constraint(model, data)
    data = smooth.transmission(model, data)
    replace = {"_impl.actuator_velocity": data._impl.actuator_moment @ data.qvel}
    if effects.tendons:
        replace["_impl.ten_velocity"] = data._impl.ten_J @ data.qvel
    data = data.tree_replace(replace)
    data = smooth.com_vel(model, data)
    if effects.passive:
        data = passive.passive(model, data)
    data = smooth.rne(model, data, flg_acc=not mass)
    if effects.tendons:
        data = smooth.tendon_bias(model, data)
    data = mjx_forward.fwd_actuation(model, data)
    if not mass:
        return data
    data = mjx_forward.fwd_acceleration(model, data)
    if effects.constraints and data._impl.efc_J.size:
        return solve_implicitly(model, data)
    return data.replace(qacc=data.qacc_smooth)


def implicit_derivative_applies(model: mujoco.MjModel, effects: SceneEffects) -> bool:
    """Whether qacc solves M(q) qacc = f(q, qvel, ctrl) exactly, so its derivative is implicit.

    Then d qacc = -M^-1 d(M qacc - f) at fixed qacc: inverse dynamics (RNE) is
    differentiated instead of the mass matrix, its factorisation and the solve.
    Constraints, actuator activations, tendons (their armature enters M) and
    Euler's implicit damping (it solves with M + dt D) change that equation.
    """
    return not (effects.constraints or effects.activation or effects.tendons) and bool(
        model.opt.disableflags & _DISABLE.mjDSBL_EULERDAMP) and int(model.opt.integrator) == int(
        mujoco.mjtIntegrator.mjINT_EULER)


def generated_step_applies(model: mujoco.MjModel, effects: SceneEffects | None) -> bool:
    """Whether ``stablebptt.physics.rigid_body`` generates this scene's rigid-body terms (``rigid_body.unsupported`` says why not)."""
    return effects is not None and not rigid_body.unsupported(model, effects)


def make_step(model: mujoco.MjModel, effects: SceneEffects | None, pipeline: str = "lean",
              implicit: bool = True, mjx_model=None) -> Callable[[State, jax.Array], State]:
    """``step(state, ctrl) -> state`` through MJX's JAX implementation.

    Args:
      model: the (lean or original) MuJoCo model.
      effects: the scene analysis; required for ``pipeline="lean"``.
      pipeline: ``"lean"`` generates the step body by body where
        ``generated_step_applies`` (``stablebptt.physics.rigid_body``; constraints from MJX's
        stages fed the generated terms), else is ``"stages"``;
        ``"stages"`` runs only MJX's needed stages (Euler integrator) and,
        where ``implicit_derivative_applies``, differentiates through inverse
        dynamics (a custom JVP, so forward and reverse mode both use it);
        ``"mjx"`` calls ``mjx.step`` unchanged (any integrator).
      implicit: False differentiates MJX's stages by plain autodiff through
        the mass matrix and its solve (a baseline for benchmarks and tests).
      mjx_model: ``model`` already put on MJX (``put_model``), if it is.
    """
    if pipeline == "lean" and not (implicit and generated_step_applies(model, effects)):
        pipeline = "stages"
    if pipeline == "lean" and not effects.constraints:
        return rigid_body.make_step(model)
    mjx_model = put_model(model) if mjx_model is None else mjx_model
    if pipeline == "lean":
        return _generated_with_mjx_constraints(model, mjx_model)
    template = mjx.make_data(mjx_model)
    is_euler = int(model.opt.integrator) == int(mujoco.mjtIntegrator.mjINT_EULER)
    if pipeline == "stages" and not is_euler:
        pipeline = "mjx"  # RK4 and implicitfast call mjx.forward inside: flags still apply

    def data_of(state: State, ctrl: jax.Array) -> mjx.Data:
        return template.replace(qpos=state.qpos, qvel=state.qvel, act=state.act, ctrl=ctrl)

    def advance(data: mjx.Data) -> State:
        data = mjx_forward.euler(mjx_model, data)
        return State(data.qpos, data.qvel, data.act)

    if pipeline == "mjx":
        def step(state: State, ctrl: jax.Array) -> State:
            data = mjx.step(mjx_model, data_of(state, ctrl))
            return State(data.qpos, data.qvel, data.act)
        return traced_differentiably(step)

    def step(state: State, ctrl: jax.Array) -> State:
        return advance(_lean_forward(mjx_model, data_of(state, ctrl), effects))

    if not (implicit and implicit_derivative_applies(model, effects)):
        return traced_differentiably(step)

    implicit_step = jax.custom_jvp(step)

    def implicit_jvp(primals, tangents):
        state, ctrl = primals
        state_dot, ctrl_dot = tangents
        data = _lean_forward(mjx_model, data_of(state, ctrl), effects)

        def residual(qpos, qvel, ctrl):  # M(q) qacc + c(q, qvel) - passive - actuator, qacc held fixed
            inverse = _lean_forward(mjx_model, data_of(State(qpos, qvel, state.act), ctrl).replace(qacc=data.qacc),
                                    effects, mass=False)
            return inverse.qfrc_bias - inverse.qfrc_passive - inverse.qfrc_actuator

        # Differentiate the residual only in the inputs that vary: with the
        # position held, kinematics and inertias are not differentiated at all.
        inputs = {"qpos": state.qpos, "qvel": state.qvel, "ctrl": ctrl}
        varying = {name: tangent for name, tangent in
                   (("qpos", state_dot.qpos), ("qvel", state_dot.qvel), ("ctrl", ctrl_dot)) if not _is_zero(tangent)}
        residual_dot = jnp.zeros_like(data.qacc)
        if varying:
            of_varying = lambda moving: residual(**{**inputs, **moving})
            residual_dot = jax.jvp(of_varying, ({name: inputs[name] for name in varying},), (varying,))[1]
        qacc_dot = -smooth.solve_m(mjx_model, data, residual_dot)
        dense = lambda tangent, primal: jnp.zeros_like(primal) if _is_zero(tangent) else tangent
        integrate = lambda qpos, qvel, qacc: advance(data.replace(qpos=qpos, qvel=qvel, qacc=qacc))
        return jax.jvp(integrate, (state.qpos, state.qvel, data.qacc),
                       (dense(state_dot.qpos, state.qpos), dense(state_dot.qvel, state.qvel), qacc_dot))

    implicit_step.defjvp(implicit_jvp, symbolic_zeros=True)
    return traced_differentiably(implicit_step)


def _generated_with_mjx_constraints(model: mujoco.MjModel, mjx_model: mjx.Model) -> Callable[[State, jax.Array], State]:
    """The generated rigid-body terms (``scene_terms.RigidBody``) through MJX's collision, constraint rows and
    solver (differentiated implicitly), then MuJoCo's Euler or RK4.

    Without MJX's scans over the tree, XLA compiles far less: hopper's first update comes 36.4 -> 21.4 s
    after a cold start (``scripts/bench.py --startup``, docs/performance.md). The generated terms are
    differentiated by plain autodiff, as the stages pipeline differentiates MJX's.
    """
    body_terms = rigid_body.make_rigid_body(model)
    # The generated mass matrix is dense; MJX reads it as such whatever the file's jacobian option.
    mjx_model = mjx_model.replace(opt=mjx_model.opt.replace(jacobian=mjx_types.JacobianType.DENSE))
    template = mjx.make_data(mjx_model)

    def solved(qpos: jax.Array, qvel: jax.Array, ctrl: jax.Array) -> mjx.Data:
        terms = body_terms(qpos, qvel, ctrl)
        data = template.replace(qpos=qpos, qvel=qvel, ctrl=ctrl, xpos=terms.xpos, xmat=terms.xmat,
                                geom_xpos=terms.geom_xpos, geom_xmat=terms.geom_xmat, site_xpos=terms.site_xpos,
                                site_xmat=terms.site_xmat, subtree_com=terms.subtree_com,
                                cdof=terms.cdof, qfrc_smooth=terms.qfrc_smooth, qacc_smooth=terms.qacc_smooth)
        if model.ntendon:  # lengths and moments for tendon limits (``rigid_body.unsupported``: no tendon forces)
            data = smooth.tendon(mjx_model, data)
        # qLD: the factor MJX's CG solver and its Euler read (XLA drops it where nothing does).
        data = data.tree_replace({"_impl.M": terms.mass_matrix,
                                  "_impl.qLD": jax.scipy.linalg.cho_factor(terms.mass_matrix)[0]})
        data = constraint.make_constraint(mjx_model, collision_driver.collision(mjx_model, data))
        if data._impl.efc_J.size:
            return solve_implicitly(mjx_model, data)
        return data.replace(qacc=data.qacc_smooth)

    if int(model.opt.integrator) == int(mujoco.mjtIntegrator.mjINT_EULER):
        def step(state: State, ctrl: jax.Array) -> State:
            data = mjx_forward.euler(mjx_model, solved(state.qpos, state.qvel, ctrl).replace(act=state.act))
            return State(data.qpos, data.qvel, data.act)
    else:
        step = rigid_body.runge_kutta_4(float(model.opt.timestep), lambda qpos, qvel, ctrl: solved(qpos, qvel, ctrl).qacc)
    return traced_differentiably(step)


def _is_zero(tangent) -> bool:
    """Whether a custom_jvp tangent is a symbolic zero (that input does not vary)."""
    return isinstance(tangent, jax.custom_derivatives.SymbolicZero)


def initial_state(model: mujoco.MjModel) -> State:
    return State(jnp.asarray(model.qpos0), jnp.zeros(model.nv), jnp.zeros(model.na))
