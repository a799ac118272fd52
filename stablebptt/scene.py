"""Simulate only what a scene calls for: scene analysis and a lean, differentiable MJX step.

``analyze(model)`` reads an ``mujoco.MjModel`` and finds which effects it can
need at all; ``lean_model`` switches the others off through MuJoCo's disable
flags (on a copy: the user's file and model are untouched); ``make_step``
builds a step over the
minimal state (qpos, qvel, act) that runs only the pipeline stages the scene
needs, skipping those no flag reaches (camera and light poses, sensors,
tendons, collision and constraint assembly).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from stablebptt import tree
from stablebptt import mujoco_log  # noqa: F401  (MuJoCo's warnings to stderr, never to MUJOCO_LOG.TXT)
from stablebptt.constraint_derivatives import solve_implicitly, traced_differentiably
from stablebptt.errors import InputError
from stablebptt.mjx_internals import collision_driver, constraint, mjx, passive, smooth
from stablebptt.mjx_internals import forward as mjx_forward
from stablebptt.mjx_internals import types as mjx_types
from stablebptt.flows import KnownColumns

_DISABLE = mujoco.mjtDisableBit
_ENABLE = mujoco.mjtEnableBit
_SLIDE, _FREE = int(mujoco.mjtJoint.mjJNT_SLIDE), int(mujoco.mjtJoint.mjJNT_FREE)
INTEGRATORS = {"euler": mujoco.mjtIntegrator.mjINT_EULER, "rk4": mujoco.mjtIntegrator.mjINT_RK4,
               "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST}


@dataclass(frozen=True)
class SceneEffects:
    """Which optional effects a scene can produce. False means: provably never."""

    contacts: bool
    joint_limits: bool
    tendon_limits: bool
    equality: bool
    friction_loss: bool
    springs: bool
    dampers: bool
    gravity_compensation: bool
    fluid: bool
    control_clamp: bool
    activation: bool
    tendons: bool
    sensors: bool

    @property
    def constraints(self) -> bool:
        """Whether the constraint solver can ever have rows."""
        return self.contacts or self.joint_limits or self.tendon_limits or self.equality or self.friction_loss

    @property
    def passive(self) -> bool:
        return self.springs or self.dampers or self.gravity_compensation or self.fluid


# (SceneEffects field, MuJoCo disable flag switched on when the effect is absent)
_FLAGS = (
    ("contacts", _DISABLE.mjDSBL_CONTACT),
    ("joint_limits", None),  # LIMIT covers joints and tendons: set below when both are absent
    ("equality", _DISABLE.mjDSBL_EQUALITY),
    ("friction_loss", _DISABLE.mjDSBL_FRICTIONLOSS),
    ("control_clamp", _DISABLE.mjDSBL_CLAMPCTRL),
)
_LABELS = {
    "contacts": "contacts", "joint_limits": "joint limits", "tendon_limits": "tendon limits",
    "equality": "equality constraints", "friction_loss": "friction loss", "springs": "springs",
    "dampers": "dampers", "gravity_compensation": "gravity compensation", "fluid": "fluid forces",
    "control_clamp": "control clamping", "activation": "actuator activation", "tendons": "tendons",
}


def analyze(model: mujoco.MjModel) -> SceneEffects:
    """Find the effects ``model`` can produce, from its structure and parameters alone."""
    disabled = lambda bit: bool(model.opt.disableflags & bit)
    contacts = not disabled(_DISABLE.mjDSBL_CONTACT) and not disabled(_DISABLE.mjDSBL_CONSTRAINT) and (
        next(iter(collision_driver.geom_pairs(model)), None) is not None)
    constraints_on = not disabled(_DISABLE.mjDSBL_CONSTRAINT)
    return SceneEffects(
        contacts=contacts,
        joint_limits=constraints_on and bool(np.any(model.jnt_limited)),
        tendon_limits=constraints_on and bool(model.ntendon and np.any(model.tendon_limited)),
        equality=constraints_on and bool(model.neq and np.any(model.eq_active0)),
        friction_loss=constraints_on and bool(np.any(model.dof_frictionloss > 0)
                                              or (model.ntendon and np.any(model.tendon_frictionloss > 0))),
        springs=bool(np.any(model.jnt_stiffness != 0) or (model.ntendon and np.any(model.tendon_stiffness != 0))),
        dampers=bool(np.any(model.dof_damping != 0) or (model.ntendon and np.any(model.tendon_damping != 0))),
        gravity_compensation=bool(np.any(model.body_gravcomp != 0)),
        fluid=bool(model.opt.density > 0 or model.opt.viscosity > 0),
        control_clamp=bool(model.nu and np.any(model.actuator_ctrllimited)),
        activation=bool(model.na),
        tendons=bool(model.ntendon),
        sensors=bool(model.nsensor),
    )


def symmetries(model: mujoco.MjModel, effects: SceneEffects) -> tuple[KnownColumns, list[str]]:
    """Columns of the step's state Jacobian that translation and Galilean symmetry fix.

    A slide joint (or a free joint's position) of a body hanging from the world,
    with no rotation before it, moves that body's whole tree along a fixed world
    direction. Unless something ties the tree to where the world is (contacts,
    equality constraints, tendons, a limit or spring on the joint, an actuator
    whose force depends on its length), forces do not change under that shift,
    so the step maps qpos + d e_k to (next qpos) + d e_k: column e_k.

    Adding a velocity along the same direction is a Galilean boost of the whole
    tree. Unless a force depends on velocity relative to the world (fluid
    forces, damping or friction loss on the joint, contacts, equality
    constraints, tendons, a limit, an actuator whose force depends on its
    velocity), accelerations do not change, so the next velocity moves by d and
    the next position by dt d (every integrator advances positions with the
    velocities it reaches).

    Returns:
      the known columns over the flattened state (qpos, qvel, act), and the
      names of the joints they belong to.
    """
    state_size = model.nq + model.nv + model.na
    entries, names = [], []
    nothing = KnownColumns(np.zeros(0, int), np.zeros((state_size, 0)))
    if effects.contacts or effects.equality or effects.tendons:
        return nothing, names
    gain, bias, gain_prm, bias_prm = (model.actuator_gaintype, model.actuator_biastype, model.actuator_gainprm,
                                      model.actuator_biasprm)
    other_gain = (gain != mujoco.mjtGain.mjGAIN_FIXED) & (gain != mujoco.mjtGain.mjGAIN_AFFINE)
    other_bias = (bias != mujoco.mjtBias.mjBIAS_NONE) & (bias != mujoco.mjtBias.mjBIAS_AFFINE)
    opaque = other_gain | other_bias | (model.actuator_dyntype == mujoco.mjtDyn.mjDYN_MUSCLE)
    affine_gain, affine_bias = gain == mujoco.mjtGain.mjGAIN_AFFINE, bias == mujoco.mjtBias.mjBIAS_AFFINE
    # Affine parameters: [constant, length, velocity].
    by_length = opaque | (affine_gain & (gain_prm[:, 1] != 0)) | (affine_bias & (bias_prm[:, 1] != 0))
    by_velocity = opaque | (affine_gain & (gain_prm[:, 2] != 0)) | (affine_bias & (bias_prm[:, 2] != 0))
    on_joint = np.isin(model.actuator_trntype, (mujoco.mjtTrn.mjTRN_JOINT, mujoco.mjtTrn.mjTRN_JOINTINPARENT))
    if np.any((by_length | by_velocity) & ~on_joint):  # a site, body or slider-crank: where the tree is may matter
        return nothing, names
    length_driven = set(model.actuator_trnid[by_length, 0].tolist())
    velocity_driven = set(model.actuator_trnid[by_velocity, 0].tolist())
    dt = float(model.opt.timestep)
    for body in range(1, model.nbody):
        if model.body_parentid[body] != 0:
            continue
        first = model.body_jntadr[body]
        for joint in range(first, first + model.body_jntnum[body]):
            known_before = len(entries)
            kind, qpos_at, dof_at = int(model.jnt_type[joint]), model.jnt_qposadr[joint], model.jnt_dofadr[joint]
            if kind not in (_SLIDE, _FREE):
                break  # later slides move along turning axes, away from this joint's anchor
            tied = bool(model.jnt_limited[joint])
            for axis in range(3 if kind == _FREE else 1):
                qpos_k, dof_k = qpos_at + axis, dof_at + axis
                translation = np.zeros(state_size)
                translation[qpos_k] = 1.0
                if not (tied or model.jnt_stiffness[joint] != 0 or joint in length_driven):
                    entries.append((qpos_k, translation))
                if not (tied or effects.fluid or model.dof_damping[dof_k] != 0 or model.dof_frictionloss[dof_k] != 0
                        or joint in velocity_driven):
                    boost = dt * translation
                    boost[model.nq + dof_k] = 1.0
                    entries.append((model.nq + dof_k, boost))
            if len(entries) > known_before:
                names.append(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, joint) or f"joint {joint}")
    if not entries:
        return nothing, names
    return KnownColumns(np.array([i for i, _ in entries]), np.stack([c for _, c in entries], axis=1)), names


# Enable flags that only compute diagnostics (no force, state or step depends on
# them): switched off on the simulated copy and named in the scene line.
_DIAGNOSTICS = {int(_ENABLE.mjENBL_ENERGY): "energy", int(_ENABLE.mjENBL_FWDINV): "forward-inverse comparison"}
# What to tell a user about the enable flags MJX cannot simulate.
_ENABLE_ADVICE = {int(_ENABLE.mjENBL_OVERRIDE): "contact override: remove <flag override=\"enable\"/>",
                  int(_ENABLE.mjENBL_DIAGEXACT): "exact constraint diagonal: remove <flag diagexact=\"enable\"/>",
                  int(_ENABLE.mjENBL_SPECULATIVE): "speculative contacts: remove <flag speculative=\"enable\"/>"}
_GEOM_NAMES = {int(t): t.name[len("mjGEOM_"):].lower() for t in (
    mujoco.mjtGeom.mjGEOM_PLANE, mujoco.mjtGeom.mjGEOM_HFIELD, mujoco.mjtGeom.mjGEOM_SPHERE,
    mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_ELLIPSOID, mujoco.mjtGeom.mjGEOM_CYLINDER,
    mujoco.mjtGeom.mjGEOM_BOX, mujoco.mjtGeom.mjGEOM_MESH, mujoco.mjtGeom.mjGEOM_SDF)}


def diagnostics(model: mujoco.MjModel) -> list[str]:
    """The diagnostics ``model`` enables: they change no dynamics, so the simulated copy skips them."""
    return [label for bit, label in _DIAGNOSTICS.items() if model.opt.enableflags & bit]


def diagnostics_bits(model: mujoco.MjModel) -> list[int]:
    """The enable flags of ``diagnostics(model)``."""
    return [bit for bit in _DIAGNOSTICS if model.opt.enableflags & bit]


def _name(model: mujoco.MjModel, kind, index: int) -> str:
    return mujoco.mj_id2name(model, kind, index) or f"#{index}"


def check_supported(model: mujoco.MjModel) -> None:
    """Raise ``InputError`` naming the first feature of ``model`` that MJX cannot simulate, and what to change.

    Call it on the copy that will be simulated (``lean_model``'s), before
    ``mjx.put_model``: it mirrors MJX's own checks, so no MJX traceback reaches a user.
    """
    def refuse(feature: str):
        raise InputError(f"MJX cannot simulate {feature}")

    if model.nflex:
        refuse("flexible bodies (<flex>, <flexcomp>): remove them")
    for bit, advice in _ENABLE_ADVICE.items():
        if model.opt.enableflags & bit:
            refuse(advice)
    supported_integrators = {int(v) for v in INTEGRATORS.values()}
    if int(model.opt.integrator) not in supported_integrators:
        refuse(f"integrator {mujoco.mjtIntegrator(model.opt.integrator).name[len('mjINT_'):].lower()}: "
               "choose euler, rk4 or implicitfast (--integrator)")
    if int(model.opt.solver) == int(mujoco.mjtSolver.mjSOL_PGS):
        refuse('the PGS constraint solver: set <option solver="Newton"/> or "CG"')
    fluid = model.opt.density > 0 or model.opt.viscosity > 0 or np.any(model.opt.wind)
    if fluid and int(model.opt.integrator) == int(mujoco.mjtIntegrator.mjINT_IMPLICITFAST):
        refuse("fluid forces with the implicitfast integrator: choose euler or rk4 (--integrator)")
    geom = mujoco.mjtObj.mjOBJ_GEOM
    for g1, g2, _ in collision_driver.geom_pairs(model):
        t1, t2 = int(model.geom_type[g1]), int(model.geom_type[g2])
        if not collision_driver.has_collision_fn(t1, t2):
            refuse(f"{_GEOM_NAMES.get(t1, t1)}-{_GEOM_NAMES.get(t2, t2)} contacts (geoms '{_name(model, geom, g1)}' and "
                   f"'{_name(model, geom, g2)}'): change one geom's type, or stop the pair colliding "
                   "(contype/conaffinity or <exclude>)")
        if {t1, t2} & {int(mujoco.mjtGeom.mjGEOM_MESH), int(mujoco.mjtGeom.mjGEOM_HFIELD)} and (
                model.geom_margin[g1] + model.geom_margin[g2] > 0):
            refuse(f"a contact margin on a mesh or height field (geoms '{_name(model, geom, g1)}' and "
                   f"'{_name(model, geom, g2)}'): set margin=\"0\"")
    for values, supported, kind, what in (
            (model.actuator_gaintype, mjx_types.GainType, mujoco.mjtGain, "actuator gain"),
            (model.actuator_biastype, mjx_types.BiasType, mujoco.mjtBias, "actuator bias"),
            (model.actuator_dyntype, mjx_types.DynType, mujoco.mjtDyn, "actuator dynamics"),
            (model.actuator_trntype, mjx_types.TrnType, mujoco.mjtTrn, "actuator transmission"),
            (model.eq_type, mjx_types.EqType, mujoco.mjtEq, "equality constraint"),
            (model.wrap_type, mjx_types.WrapType, mujoco.mjtWrap, "tendon wrap")):
        missing = sorted(set(int(v) for v in values) - set(int(s) for s in supported))
        if missing:
            refuse(f"{what} type {kind(missing[0]).name.split('_', 1)[1].lower()}: replace it")


def put_model(model: mujoco.MjModel):
    """``mjx.put_model`` after ``check_supported``; anything MJX still refuses becomes one ``InputError`` line."""
    check_supported(model)
    try:
        return mjx.put_model(model, impl="jax")
    except NotImplementedError as error:
        raise InputError(f"MJX cannot simulate this model: {error}") from None


def constraint_rows(model) -> int:
    """The rows of MJX's constraint system for ``model`` (every candidate contact's and limit's, active or not):
    the size of the solver's matrices, and so of its per-step work. ``model``: a MuJoCo model or one on MJX."""
    mjx_model = put_model(model) if isinstance(model, mujoco.MjModel) else model
    return int(mjx.make_data(mjx_model)._impl.efc_J.shape[0])


def with_options(model: mujoco.MjModel, integrator: str | None = None, timestep: float | None = None) -> mujoco.MjModel:
    """A copy of ``model`` with its integrator and time step overridden where given."""
    copied = copy.copy(model)
    if integrator is not None:
        copied.opt.integrator = INTEGRATORS[integrator]
    if timestep is not None:
        copied.opt.timestep = timestep
    return copied


def lean_model(model: mujoco.MjModel, effects: SceneEffects, integrator: str | None = None,
               timestep: float | None = None, solver_iterations: int | None = None) -> mujoco.MjModel:
    """A copy of ``model`` with every absent effect and every diagnostic switched off.

    Args:
      solver_iterations: None keeps the model's own constraint solver. A
        number N sets exactly N Newton iterations (tolerance 0, which MuJoCo's
        C step honours too): cheaper, and different physics where N does not
        reach the solution. Either way the solver's iterations are not
        differentiated (``constraint_derivatives.solve_implicitly``).
    """
    lean = with_options(model, integrator, timestep)
    for bit in diagnostics_bits(lean):
        lean.opt.enableflags &= ~bit
    # Sensors feed no loss, so they are never simulated; MJX still checks every
    # sensor's type, so the copy's become clocks, which it supports.
    lean.opt.disableflags |= _DISABLE.mjDSBL_SENSOR
    lean.sensor_type[:] = mujoco.mjtSensor.mjSENS_CLOCK
    if not effects.contacts:
        # No pair can ever touch (or contacts are off): MJX need not know the geoms' collision types.
        lean.geom_contype[:] = 0
        lean.geom_conaffinity[:] = 0
    for name, bit in _FLAGS:
        if bit is not None and not getattr(effects, name):
            lean.opt.disableflags |= bit
    if not (effects.joint_limits or effects.tendon_limits):
        lean.opt.disableflags |= _DISABLE.mjDSBL_LIMIT
    if not effects.passive:
        # MJX zeroes ALL passive forces (springs, dampers, gravity compensation,
        # fluid) when either flag is set, unlike MuJoCo's C step: only both, and
        # only when the scene has none of them.
        lean.opt.disableflags |= _DISABLE.mjDSBL_SPRING | _DISABLE.mjDSBL_DAMPER
    if not effects.constraints:
        lean.opt.disableflags |= _DISABLE.mjDSBL_CONSTRAINT
    elif solver_iterations is not None:
        _fix_iterations(lean, solver_iterations)
    if not effects.dampers:
        # Euler's implicit damping refactors the mass matrix: pointless without damping.
        lean.opt.disableflags |= _DISABLE.mjDSBL_EULERDAMP
    # The dense mass matrix means a LAPACK call (CPU) or cuBLAS triangular solves
    # (GPU) per step and more in its derivatives; MJX's sparse path is plain fused
    # arithmetic, and faster on both (scripts/bench.py, rows "dense mass matrix").
    lean.opt.jacobian = mujoco.mjtJacobian.mjJAC_SPARSE
    return lean


def _fix_iterations(model: mujoco.MjModel, iterations: int) -> None:
    model.opt.solver = mujoco.mjtSolver.mjSOL_NEWTON
    model.opt.iterations = iterations
    model.opt.tolerance = 0.0  # never stop early: exactly ``iterations``


def fixed_iterations(model: mujoco.MjModel) -> bool:
    """Whether ``model``'s Newton solver runs a fixed number of iterations (tolerance 0)."""
    return model.opt.tolerance == 0 and int(model.opt.solver) == int(mujoco.mjtSolver.mjSOL_NEWTON)


def describe(effects: SceneEffects, model: mujoco.MjModel, original: mujoco.MjModel | None = None) -> str:
    """One line: what is simulated, what is skipped, and any solver setting chosen for gradients.

    ``original``, the user's model, names the diagnostics the simulated copy skips.
    """
    simulated = [label for name, label in _LABELS.items() if getattr(effects, name)]
    skipped = [label for name, label in _LABELS.items() if not getattr(effects, name)]
    skipped += ["sensors"] + [f"{label} diagnostic" for label in diagnostics(original if original is not None else model)]
    integrator = {v: k for k, v in INTEGRATORS.items()}.get(int(model.opt.integrator), str(model.opt.integrator))
    line = (f"scene: {model.nq} qpos, {model.nv} dof, {model.nu} actuators, {integrator} at dt {model.opt.timestep:g}; "
            f"simulated: rigid-body dynamics{''.join(', ' + s for s in simulated)}; skipped: {', '.join(skipped) or 'nothing'}")
    if effects.constraints:
        if fixed_iterations(model):
            count = int(model.opt.iterations)
            line += f"; constraint solver: {count} Newton iteration{'s' if count > 1 else ''}, fixed"
            if original is not None and not fixed_iterations(original):
                line += f" (the model's own: {_solver_name(original)}, tolerance {original.opt.tolerance:g})"
        else:
            line += (f"; constraint solver: the model's own ({_solver_name(model)}, at most {model.opt.iterations} iterations, "
                     f"tolerance {model.opt.tolerance:g})")
    return line


def _solver_name(model: mujoco.MjModel) -> str:
    name = mujoco.mjtSolver(model.opt.solver).name[len("mjSOL_"):].capitalize()
    return "CG" if name == "Cg" else name


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
    """Whether ``stablebptt.tree`` generates this scene's step: a small contact-free tree of hinges and slides."""
    return effects is not None and not tree.unsupported(model, effects)


def make_step(model: mujoco.MjModel, effects: SceneEffects | None, pipeline: str = "lean",
              implicit: bool = True, mjx_model=None) -> Callable[[State, jax.Array], State]:
    """``step(state, ctrl) -> state`` through MJX's JAX implementation.

    Args:
      model: the (lean or original) MuJoCo model.
      effects: the scene analysis; required for ``pipeline="lean"``.
      pipeline: ``"lean"`` generates the step body by body where
        ``generated_step_applies`` (``stablebptt.tree``), else is ``"stages"``;
        ``"stages"`` runs only MJX's needed stages (Euler integrator) and,
        where ``implicit_derivative_applies``, differentiates through inverse
        dynamics (a custom JVP, so forward and reverse mode both use it);
        ``"mjx"`` calls ``mjx.step`` unchanged (any integrator).
      implicit: False differentiates MJX's stages by plain autodiff through
        the mass matrix and its solve (a baseline for benchmarks and tests).
      mjx_model: ``model`` already put on MJX (``put_model``), if it is.
    """
    if pipeline == "lean":
        if implicit and generated_step_applies(model, effects):
            return tree.make_step(model)
        pipeline = "stages"
    mjx_model = put_model(model) if mjx_model is None else mjx_model
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


def _is_zero(tangent) -> bool:
    """Whether a custom_jvp tangent is a symbolic zero (that input does not vary)."""
    return isinstance(tangent, jax.custom_derivatives.SymbolicZero)


def initial_state(model: mujoco.MjModel) -> State:
    return State(jnp.asarray(model.qpos0), jnp.zeros(model.nv), jnp.zeros(model.na))
