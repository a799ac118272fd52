"""A step generated per scene for kinematic trees of hinge, slide, ball and free joints.

MJX runs every stage over all bodies at once by scanning over tree levels, with
gathers of parents and a sparse mass-matrix factorisation: differentiated, a
program XLA takes long to compile, and on a GPU many tiny kernels. Here the
rigid-body terms are generated per scene while tracing, the model's numbers as
constants, in one of two forms of the same physics (``make_scene``):

- ``WrittenOut`` (``written_out``), for trees of a few dofs: every recursion written out body by
  body, scalar by scalar, with the model's zeros folded away - straight-line
  arithmetic on each example's scalars, which XLA fuses into few kernels;
- ``ArrayTerms`` (``array_terms``), for larger trees: kinematics body by body on 3-vectors and 3x3
  matrices, then everything else as one array operation over all bodies and dofs
  through constant masks of which dof moves which body. Its program grows with
  the number of joints, not with their arithmetic: written out, humanoid's terms
  are 21,000 traced operations that XLA compiles in 95 s; in arrays, 900 in 2 s
  (``benchmarks/step_compile.py --forms``).

The physics is MuJoCo's, term by term (tests compare with ``mujoco.mj_step`` in
float64): forward kinematics, the composite-rigid-body mass matrix plus
armature, recursive Newton-Euler bias forces with gravity, springs and dampers,
actuators of joints and fixed tendons (fixed gain, affine bias, control and
force clamps), and the Euler (with its implicit joint damping) or RK4 integrator.
Spatial vectors are (angular, linear) about the world origin.

A contact-free scene's derivative is the inverse-dynamics one
(``lean_step.implicit_derivative_applies`` explains it): the acceleration solves
M~(q) qacc = f(q, qvel, ctrl), so d qacc = -M~^-1 d(ID(q, qvel, qacc) - f) at
fixed qacc, and the mass matrix, its factorisation and the solve are never
differentiated. A scene with contacts, joint limits or friction loss takes the
generated terms in MuJoCo's frames (``RigidBody``) into MJX's collision,
constraint rows and solver (``lean_step``), whose Euler step integrates the
quaternions of free and ball joints.
"""
from __future__ import annotations

from typing import Callable

import jax
import mujoco
import numpy as np

from stablebptt.physics import integrators
from stablebptt.physics.array_terms import ArrayTerms
from stablebptt.physics.folding import solve_spd
from stablebptt.physics.scene_terms import BALL, EULER, FREE, RK4, SceneTerms, joints_pulled
from stablebptt.physics.written_out import WrittenOut

# Up to this many degrees of freedom, per backend, the terms are written out scalar by scalar
# (``WrittenOut``), beyond it in arrays (``ArrayTerms``). Where each pays was measured side by side
# (docs/performance.md): on a CPU arrays reach the first update sooner from hopper's 7 dofs up, and
# later for the cart-poles; on a GPU the written-out cart-pole grid compiles and trains faster.
WRITTEN_OUT_DOFS = {"cpu": 5, "gpu": 12}


def unsupported(model: mujoco.MjModel, effects) -> str:
    """Why the generated step does not cover ``model`` ('' when it does); ``effects`` from ``scene.analyze``.

    Contacts, joint limits, friction loss, tendon limits and equality constraints are MJX's own stages fed
    the generated terms (a tendon's length and moments are MJX's, from the generated site and geom
    frames); welds (they read body quaternions, which are not generated) and tendons that carry forces of
    their own are left to MJX's stages. Actuators pull joints or fixed tendons, whose moments are
    constant. Free and ball joints are generated where MJX's stages and its Euler step take over from
    the generated terms (their quaternions integrate on the sphere).
    """
    present = [name for name in ("activation", "gravity_compensation", "fluid") if getattr(effects, name)]
    if present:
        return present[0].replace("_", " ")
    if effects.equality and np.any(model.eq_type == int(mujoco.mjtEq.mjEQ_WELD)):
        return "weld equality constraints"
    if effects.tendons and (any(np.any(np.asarray(a) != 0) for a in (
            model.tendon_stiffness, model.tendon_stiffnesspoly, model.tendon_springyield, model.tendon_damping,
            model.tendon_dampingpoly, model.tendon_frictionloss, model.tendon_armature))
            or np.any(model.tendon_plasticadr >= 0)):
        return "tendons with stiffness, damping, friction loss or armature"
    turning = np.isin(model.jnt_type, (FREE, BALL))
    if model.nv == 0:
        return "no degrees of freedom"
    if np.any(turning):
        if not effects.constraints:
            return "free or ball joints in a scene without contacts, limits or friction loss"
        if int(model.opt.integrator) != EULER:
            return "free or ball joints with an integrator other than Euler"
        if np.any(model.jnt_stiffness[turning]):
            return "springs on free or ball joints"
        on_joints = model.actuator_trntype == int(mujoco.mjtTrn.mjTRN_JOINT)
        if np.any(turning[model.actuator_trnid[on_joints, 0]]):
            return "actuators on free or ball joints"
    if int(model.opt.integrator) not in (EULER, RK4):
        return f"the {mujoco.mjtIntegrator(model.opt.integrator).name} integrator"
    if model.opt.enableflags:
        return "enabled optional features"
    nonlinear = [model.dof_dampingpoly, model.jnt_stiffnesspoly, model.jnt_springyield, model.jnt_actgravcomp]
    if any(np.any(np.asarray(a) != 0) for a in nonlinear) or np.any(model.jnt_plasticadr >= 0):
        return "nonlinear or plastic springs and dampers"
    pulled = model.actuator_trnid[model.actuator_trntype == int(mujoco.mjtTrn.mjTRN_TENDON), 0]
    if np.any(model.tendon_actfrclimited[pulled]):
        return "actuator force limits on tendons"
    if model.nu and not (all(joints_pulled(model, actuator) is not None for actuator in range(model.nu))
                         and np.all(model.actuator_dyntype == int(mujoco.mjtDyn.mjDYN_NONE))
                         and np.all(model.actuator_gaintype == int(mujoco.mjtGain.mjGAIN_FIXED))
                         and np.all(np.isin(model.actuator_biastype, (int(mujoco.mjtBias.mjBIAS_NONE),
                                                                      int(mujoco.mjtBias.mjBIAS_AFFINE))))):
        return "actuators other than fixed-gain actuators of joints or fixed tendons"
    return ""


def make_scene(model: mujoco.MjModel) -> SceneTerms:
    """The rigid-body terms of ``model`` in the form that pays for its size on this backend (``WRITTEN_OUT_DOFS``)."""
    written_out = WRITTEN_OUT_DOFS.get(jax.default_backend(), WRITTEN_OUT_DOFS["gpu"])
    return (WrittenOut if model.nv <= written_out else ArrayTerms)(model)


def make_rigid_body(model: mujoco.MjModel) -> Callable:
    """``rigid_body(qpos, qvel, ctrl) -> RigidBody`` of one example, differentiated by plain autodiff."""
    return make_scene(model).rigid_body


def make_acceleration(model: mujoco.MjModel) -> Callable:
    """``acceleration(qpos, qvel, ctrl) -> qacc`` of one example, with the inverse-dynamics derivative."""
    scene = make_scene(model)

    def solve(placed, rhs):
        return solve_spd(scene.mass_matrix(placed, scene.diagonal), rhs)

    def residual(qpos, qvel, ctrl, qacc, placed):
        return scene.inverse_dynamics(placed, qvel, qacc) - scene.applied_forces(qpos, qvel, ctrl)

    def forward(qpos, qvel, ctrl, placed):
        return solve(placed, -residual(qpos, qvel, ctrl, [0.0] * scene.nv, placed))

    @jax.custom_jvp
    def acceleration(qpos, qvel, ctrl):
        return forward(qpos, qvel, ctrl, scene.place(qpos))

    @acceleration.defjvp
    def acceleration_jvp(primals, tangents):
        qpos, qvel, ctrl = primals
        placed = scene.place(qpos)  # once for the value and the solve; the residual's tangent places again
        qacc = forward(qpos, qvel, ctrl, placed)
        _, residual_dot = jax.jvp(lambda q, v, u: residual(q, v, u, qacc, scene.place(q)), primals, tangents)
        return qacc, -solve(placed, residual_dot)

    return acceleration


def make_step(model: mujoco.MjModel) -> Callable:
    """``step(state, ctrl) -> state`` of one example (a ``scene.State``), MuJoCo's Euler or RK4."""
    if np.any(np.isin(model.jnt_type, (FREE, BALL))):  # qpos + h qvel would leave the quaternions' sphere
        raise ValueError("free and ball joints take MJX's Euler step (tree.unsupported)")
    acceleration = make_acceleration(model)
    h = float(model.opt.timestep)

    if int(model.opt.integrator) == EULER:
        def step(state, ctrl):
            qvel = state.qvel + h * acceleration(state.qpos, state.qvel, ctrl)
            return state._replace(qpos=state.qpos + h * qvel, qvel=qvel)
        return step
    return runge_kutta_4(h, acceleration)


def runge_kutta_4(h: float, acceleration: Callable) -> Callable:
    """MuJoCo's RK4 step of hinges and slides over ``acceleration(qpos, qvel, ctrl) -> qacc``."""
    advance = integrators.rk4(lambda position_velocity, ctrl: (position_velocity[1], acceleration(*position_velocity, ctrl)), h)

    def step(state, ctrl):
        qpos, qvel = advance((state.qpos, state.qvel), ctrl)
        return state._replace(qpos=qpos, qvel=qvel)
    return step
