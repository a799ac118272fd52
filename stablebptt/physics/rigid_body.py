"""A step generated per scene for kinematic trees of hinge, slide, ball and free joints.

MJX runs every stage over all bodies at once by scanning over tree levels, with
gathers of parents and a sparse mass-matrix factorisation: differentiated, a
program XLA takes long to compile, and on a GPU many tiny kernels. Here the
rigid-body terms are generated per scene while tracing, the model's numbers as
constants, in one of two forms of the same physics (``make_scene``):

- ``_WrittenOut``, for trees of a few dofs: every recursion written out body by
  body, scalar by scalar, with the model's zeros folded away - straight-line
  arithmetic on each example's scalars, which XLA fuses into few kernels;
- ``_Arrays``, for larger trees: kinematics body by body on 3-vectors and 3x3
  matrices, then everything else as one array operation over all bodies and dofs
  through constant masks of which dof moves which body. Its program grows with
  the number of joints, not with their arithmetic: written out, humanoid's terms
  are 21,000 traced operations that XLA compiles in 95 s; in arrays, 900 in 2 s
  (``experiments/step_compile.py --forms``).

The physics is MuJoCo's, term by term (tests compare with ``mujoco.mj_step`` in
float64): forward kinematics, the composite-rigid-body mass matrix plus
armature, recursive Newton-Euler bias forces with gravity, springs and dampers,
actuators of joints and fixed tendons (fixed gain, affine bias, control and
force clamps), and the Euler (with its implicit joint damping) or RK4 integrator.
Spatial vectors are (angular, linear) about the world origin.

A contact-free scene's derivative is the inverse-dynamics one
(``scene.implicit_derivative_applies`` explains it): the acceleration solves
M~(q) qacc = f(q, qvel, ctrl), so d qacc = -M~^-1 d(ID(q, qvel, qacc) - f) at
fixed qacc, and the mass matrix, its factorisation and the solve are never
differentiated. A scene with contacts, joint limits or friction loss takes the
generated terms in MuJoCo's frames (``RigidBody``) into MJX's collision,
constraint rows and solver (``lean_step``), whose Euler step integrates the
quaternions of free and ball joints.
"""
from __future__ import annotations

import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from stablebptt.physics import integrators

_DISABLE = mujoco.mjtDisableBit
FREE, BALL = int(mujoco.mjtJoint.mjJNT_FREE), int(mujoco.mjtJoint.mjJNT_BALL)
SLIDE = int(mujoco.mjtJoint.mjJNT_SLIDE)
EULER, RK4 = int(mujoco.mjtIntegrator.mjINT_EULER), int(mujoco.mjtIntegrator.mjINT_RK4)
# Up to this many degrees of freedom, per backend, the terms are written out scalar by scalar
# (``_WrittenOut``), beyond it in arrays (``_Arrays``). Where each pays was measured side by side
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
    if model.nu and not (all(_joints_pulled(model, actuator) is not None for actuator in range(model.nu))
                         and np.all(model.actuator_dyntype == int(mujoco.mjtDyn.mjDYN_NONE))
                         and np.all(model.actuator_gaintype == int(mujoco.mjtGain.mjGAIN_FIXED))
                         and np.all(np.isin(model.actuator_biastype, (int(mujoco.mjtBias.mjBIAS_NONE),
                                                                      int(mujoco.mjtBias.mjBIAS_AFFINE))))):
        return "actuators other than fixed-gain actuators of joints or fixed tendons"
    return ""


def _joints_pulled(model: mujoco.MjModel, actuator: int) -> list[tuple[int, float]] | None:
    """(joint, coefficient) of what the actuator pulls where its length is linear in qpos and its moment
    constant: a joint, or a fixed tendon's joints; None for any other transmission."""
    target, kind = int(model.actuator_trnid[actuator, 0]), int(model.actuator_trntype[actuator])
    if kind == int(mujoco.mjtTrn.mjTRN_JOINT):
        return [(target, 1.0)]
    if kind != int(mujoco.mjtTrn.mjTRN_TENDON):
        return None
    wraps = range(model.tendon_adr[target], model.tendon_adr[target] + model.tendon_num[target])
    if np.any(model.wrap_type[wraps] != int(mujoco.mjtWrap.mjWRAP_JOINT)):
        return None
    return [(int(model.wrap_objid[w]), float(model.wrap_prm[w])) for w in wraps]


def _transmission(model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """Each actuator's length as a linear form in qpos [nu, nq] and its moment arms [nu, nv], gear included:
    a joint's coordinate, or a fixed tendon's sum of its joints' coordinates times their coefficients
    (hinges and slides, one coordinate per dof; free and ball joints carry no actuators, ``unsupported``)."""
    length, moment = np.zeros((model.nu, model.nq)), np.zeros((model.nu, model.nv))
    for actuator in range(model.nu):
        pulled, gear = _joints_pulled(model, actuator), float(model.actuator_gear[actuator, 0])
        if pulled is None:
            raise ValueError("an actuator pulls neither a joint nor a fixed tendon (tree.unsupported)")
        for joint, coefficient in pulled:
            length[actuator, model.jnt_qposadr[joint]] += gear * coefficient
            moment[actuator, model.jnt_dofadr[joint]] += gear * coefficient
    return length, moment


def _rotation(quat: np.ndarray) -> np.ndarray:
    matrix = np.zeros(9)
    mujoco.mju_quat2Mat(matrix, np.asarray(quat, dtype=float))
    return matrix.reshape(3, 3)


# Scalars are Python floats (the model's constants) or traced arrays. Folding the
# constants while tracing drops every product with a zero entry of an axis, a
# position or an inertia - XLA may not (0 * x is NaN for infinite x) - so a planar
# tree costs the arithmetic of its closed-form equations.
def _add(a, b):
    if isinstance(a, float) and isinstance(b, float):
        return a + b
    if isinstance(a, float) and a == 0.0:
        return b
    if isinstance(b, float) and b == 0.0:
        return a
    return a + b


def _neg(a):
    return -a


def _sub(a, b):
    return _add(a, _neg(b))


def _mul(a, b):
    if isinstance(a, float) and isinstance(b, float):
        return a * b
    for constant, other in ((a, b), (b, a)):
        if isinstance(constant, float):
            if constant == 0.0:
                return 0.0
            if constant == 1.0:
                return other
            if constant == -1.0:
                return -other
    return a * b


def _sum(terms):
    total = 0.0
    for term in terms:
        total = _add(total, term)
    return total


def _div(a, b):
    if isinstance(a, float) and isinstance(b, float):
        return a / b
    if isinstance(a, float) and a == 0.0:
        return 0.0
    return a / b


def _sqrt(a):
    return math.sqrt(a) if isinstance(a, float) else jnp.sqrt(a)


def _constant(array) -> tuple:
    return tuple(_constant(a) for a in array) if np.ndim(array) else float(array)


def _v_add(a, b):
    return tuple(_add(x, y) for x, y in zip(a, b))


def _v_sub(a, b):
    return tuple(_sub(x, y) for x, y in zip(a, b))


def _v_scale(v, factor):
    return tuple(_mul(x, factor) for x in v)


def _dot(a, b):
    return _sum(_mul(x, y) for x, y in zip(a, b))


def _cross(a, b):
    return (_sub(_mul(a[1], b[2]), _mul(a[2], b[1])), _sub(_mul(a[2], b[0]), _mul(a[0], b[2])),
            _sub(_mul(a[0], b[1]), _mul(a[1], b[0])))


def _mv(matrix, vector):
    return tuple(_dot(row, vector) for row in matrix)


def _v_scale_each(v, factors):
    return tuple(_mul(x, f) for x, f in zip(v, factors))


def _transpose(matrix):
    return tuple(zip(*matrix))


def _mm(a, b):
    columns = _transpose(b)
    return tuple(tuple(_dot(row, column) for column in columns) for row in a)


def _quaternion_rotation(quat):
    """The rotation of a traced quaternion (w, x, y, z), normalised first as MuJoCo's kinematics does."""
    norm = jnp.sqrt(sum(q * q for q in quat))
    w, x, y, z = (q / norm for q in quat)
    return ((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
            (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
            (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)))


def _axis_rotation(axis: tuple, angle):
    """Rotation by ``angle`` about the constant unit ``axis``: c (1 - a a^T) + s [a]x + a a^T."""
    cosine, sine = jnp.cos(angle), jnp.sin(angle)
    skew = ((0.0, -axis[2], axis[1]), (axis[2], 0.0, -axis[0]), (-axis[1], axis[0], 0.0))
    return tuple(tuple(_add(_add(_mul((i == j) - axis[i] * axis[j], cosine), _mul(skew[i][j], sine)),
                            axis[i] * axis[j]) for j in range(3)) for i in range(3))


_ZERO3 = (0.0, 0.0, 0.0)
_IDENTITY = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


class _Inertia:
    """A spatial inertia about the origin: rotational part, first moment m c, mass (they add)."""

    def __init__(self, rotational, moment, mass):
        self.rotational, self.moment, self.mass = rotational, moment, mass

    def __add__(self, other):
        return _Inertia(tuple(_v_add(a, b) for a, b in zip(self.rotational, other.rotational)),
                        _v_add(self.moment, other.moment), self.mass + other.mass)

    def apply(self, motion):
        angular, linear = motion
        return (_v_add(_mv(self.rotational, angular), _cross(self.moment, linear)),
                _v_sub(_v_scale(linear, self.mass), _cross(self.moment, angular)))


def _cross_motion(velocity, motion):
    (w, v), (w2, v2) = velocity, motion
    return _cross(w, w2), _v_add(_cross(w, v2), _cross(v, w2))


def _cross_force(velocity, force):
    (w, v), (n, f) = velocity, force
    return _v_add(_cross(w, n), _cross(v, f)), _cross(w, f)


def _s_dot(motion, force):
    return _add(_dot(motion[0], force[0]), _dot(motion[1], force[1]))


def _s_add(a, b):
    return _v_add(a[0], b[0]), _v_add(a[1], b[1])


def _s_scale(motion, factor):
    return _v_scale(motion[0], factor), _v_scale(motion[1], factor)


class RigidBody(NamedTuple):
    """One example's rigid-body terms, in MuJoCo's names and frames: what MJX's collision, constraint
    rows and solver read."""

    xpos: jax.Array  # [nbody, 3] body frames, the world's first
    xmat: jax.Array  # [nbody, 3, 3]
    geom_xpos: jax.Array  # [ngeom, 3]
    geom_xmat: jax.Array  # [ngeom, 3, 3]
    site_xpos: jax.Array  # [nsite, 3] (a tendon's path)
    site_xmat: jax.Array  # [nsite, 3, 3]
    subtree_com: jax.Array  # [nbody, 3]
    cdof: jax.Array  # [nv, 6] joint motion axes about their tree's centre of mass
    mass_matrix: jax.Array  # [nv, nv] armature included (not Euler's implicit damping)
    qfrc_smooth: jax.Array  # [nv] springs, dampers and actuators less the bias forces
    qacc_smooth: jax.Array  # [nv] the acceleration without constraints


class _Scene:
    """The model's numbers, read once; its bodies in MuJoCo's order (parents first). The rigid-body terms
    come in two forms of the same physics (``make_scene`` picks one): ``_WrittenOut`` and ``_Arrays``."""

    def __init__(self, model: mujoco.MjModel):
        self.model = model
        self.nv = model.nv
        disabled = lambda bit: bool(model.opt.disableflags & bit)
        self.gravity = _ZERO3 if disabled(_DISABLE.mjDSBL_GRAVITY) else _constant(model.opt.gravity)
        self.springs = not disabled(_DISABLE.mjDSBL_SPRING)
        self.dampers = not disabled(_DISABLE.mjDSBL_DAMPER)
        self.actuation = model.nu > 0 and not disabled(_DISABLE.mjDSBL_ACTUATION)
        self.clamp_ctrl = not disabled(_DISABLE.mjDSBL_CLAMPCTRL)
        self.timestep = float(model.opt.timestep)
        self.integrator = int(model.opt.integrator)
        damping = model.dof_damping if self.dampers else np.zeros(model.nv)
        # MuJoCo's Euler integrates joint damping implicitly: it solves with M + h D.
        self.implicit_damping = (self.integrator == EULER and not disabled(_DISABLE.mjDSBL_EULERDAMP)
                                 and bool(np.any(damping > 0)))
        self.diagonal = np.array(model.dof_armature) + (self.timestep * damping if self.implicit_damping else 0.0)
        self.actuator_length, self.actuator_moment = _transmission(model)
        self.joints_only = bool(np.all(model.actuator_trntype == int(mujoco.mjtTrn.mjTRN_JOINT)))
        self.bodies = list(range(1, model.nbody))
        self.joints = {b: list(range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b]))
                       for b in self.bodies}

    def applied_forces(self, qpos, qvel, ctrl):
        """Springs, dampers and actuators: MuJoCo's qfrc_passive + qfrc_actuator (in ``qvel``'s dtype)."""
        m, like = self.model, lambda a: jnp.asarray(a, qvel.dtype)
        force = jnp.zeros(self.nv, dtype=qvel.dtype)
        if self.dampers:
            force = force - like(m.dof_damping) * qvel
        if self.springs and np.any(m.jnt_stiffness):  # free and ball joints have none (``unsupported``)
            sprung = np.flatnonzero(m.jnt_stiffness)
            dofs, addresses = m.jnt_dofadr[sprung], m.jnt_qposadr[sprung]
            force = force.at[dofs].add(-like(m.jnt_stiffness[sprung]) * (qpos[addresses] - like(m.qpos_spring[addresses])))
        if self.actuation:
            if self.clamp_ctrl and np.any(m.actuator_ctrllimited):
                limited = np.asarray(m.actuator_ctrllimited, bool)
                ctrl = jnp.where(limited, jnp.clip(ctrl, like(m.actuator_ctrlrange[:, 0]), like(m.actuator_ctrlrange[:, 1])), ctrl)
            if self.joints_only:  # gathers and a scatter, the program joint actuators always had
                joint, gear = m.actuator_trnid[:, 0], like(m.actuator_gear[:, 0])
                length, velocity = gear * qpos[m.jnt_qposadr[joint]], gear * qvel[m.jnt_dofadr[joint]]
                to_dofs = lambda actuator: jnp.zeros(self.nv, dtype=qvel.dtype).at[m.jnt_dofadr[joint]].add(gear * actuator)
            else:
                length, velocity = like(self.actuator_length) @ qpos, like(self.actuator_moment) @ qvel
                to_dofs = lambda actuator: actuator @ like(self.actuator_moment)
            bias = like(m.actuator_biasprm)
            actuator = like(m.actuator_gainprm[:, 0]) * ctrl + (bias[:, 0] + bias[:, 1] * length + bias[:, 2] * velocity)
            if np.any(m.actuator_forcelimited):
                limited = np.asarray(m.actuator_forcelimited, bool)
                actuator = jnp.where(limited, jnp.clip(actuator, like(m.actuator_forcerange[:, 0]),
                                                       like(m.actuator_forcerange[:, 1])), actuator)
            generalized = to_dofs(actuator)
            if np.any(m.jnt_actfrclimited):
                limited = np.asarray(m.jnt_actfrclimited, bool)
                dofs = m.jnt_dofadr[limited]
                generalized = generalized.at[dofs].set(jnp.clip(generalized[dofs], like(m.jnt_actfrcrange[limited, 0]),
                                                                like(m.jnt_actfrcrange[limited, 1])))
            force = force + generalized
        return force


class _WrittenOut(_Scene):
    """The terms written out scalar by scalar, the model's zeros folded away while tracing."""

    def kinematics(self, qpos):
        """Per body: position, rotation, and its joints' motion axes as groups [[(dof, (angular, linear))]].

        A group's axes move together: a hinge or slide is a group of one, a ball joint's (or a free
        joint's) three rotations are one group about the body's final axes, as MuJoCo's ``cdof`` has them.
        """
        m = self.model
        position, rotation, axes = {0: _ZERO3}, {0: _IDENTITY}, {}
        for b in self.bodies:
            parent = m.body_parentid[b]
            x = _v_add(position[parent], _mv(rotation[parent], _constant(m.body_pos[b])))
            r = _mm(rotation[parent], _constant(_rotation(m.body_quat[b])))
            axes[b], turning = [], []  # turning: (group, first dof, anchor) of rotations about the final axes
            for j in self.joints[b]:
                address, dof = m.jnt_qposadr[j], m.jnt_dofadr[j]
                if m.jnt_type[j] == FREE:  # a body of the world's: qpos holds its frame itself
                    x = tuple(qpos[address + i] for i in range(3))
                    r = _quaternion_rotation([qpos[address + 3 + i] for i in range(4)])
                    axes[b] += [[(dof + i, (_ZERO3, _IDENTITY[i])) for i in range(3)], []]
                    turning.append((axes[b][-1], dof + 3, x))
                    continue
                if m.jnt_type[j] == BALL:
                    anchor = _v_add(x, _mv(r, _constant(m.jnt_pos[j])))
                    r = _mm(r, _quaternion_rotation([qpos[address + i] for i in range(4)]))
                    x = _v_sub(anchor, _mv(r, _constant(m.jnt_pos[j])))
                    axes[b].append([])
                    turning.append((axes[b][-1], dof, anchor))
                    continue
                axis = _constant(m.jnt_axis[j])
                world_axis = _mv(r, axis)
                offset = qpos[address] - float(m.qpos0[address])
                if m.jnt_type[j] == SLIDE:
                    x = _v_add(x, _v_scale(world_axis, offset))
                    axes[b].append([(dof, (_ZERO3, world_axis))])
                else:
                    anchor = _v_add(x, _mv(r, _constant(m.jnt_pos[j])))
                    r = _mm(r, _axis_rotation(axis, offset))
                    x = _v_sub(anchor, _mv(r, _constant(m.jnt_pos[j])))
                    axes[b].append([(dof, (world_axis, _cross(anchor, world_axis)))])
            columns = _transpose(r)
            for group, first, anchor in turning:
                group += [(first + i, (columns[i], _cross(anchor, columns[i]))) for i in range(3)]
            position[b], rotation[b] = x, r
        return position, rotation, axes

    def inertias(self, position, rotation):
        m = self.model
        inertias = {}
        for b in self.bodies:
            centre = _v_add(position[b], _mv(rotation[b], _constant(m.body_ipos[b])))
            frame = _mm(rotation[b], _constant(_rotation(m.body_iquat[b])))
            principal = _constant(m.body_inertia[b])
            about_centre = _mm(tuple(_v_scale_each(row, principal) for row in frame), _transpose(frame))
            mass = float(m.body_mass[b])
            # Parallel axes: I_o = I_c + m (|c|^2 1 - c c^T).
            squared = _dot(centre, centre)
            rotational = tuple(tuple(_add(about_centre[i][j], _mul(mass, _sub(squared if i == j else 0.0,
                                                                              _mul(centre[i], centre[j]))))
                                     for j in range(3)) for i in range(3))
            inertias[b] = _Inertia(rotational, _v_scale(centre, mass), mass)
        return inertias

    def place(self, qpos):
        """What the mass matrix and inverse dynamics share: joint axes and body inertias at ``qpos``."""
        position, rotation, axes = self.kinematics(qpos)
        return axes, self.inertias(position, rotation)

    def inverse_dynamics(self, placed, qvel, qacc):
        """Recursive Newton-Euler: M(q) qacc + c(q, qvel), armature excluded (MuJoCo's qfrc_bias at qacc)."""
        m = self.model
        axes, inertias = placed
        velocity, acceleration, force = {0: (_ZERO3, _ZERO3)}, {0: (_ZERO3, _v_scale(self.gravity, -1.0))}, {}
        for b in self.bodies:
            v, a = velocity[m.body_parentid[b]], acceleration[m.body_parentid[b]]
            for group in axes[b]:  # a group's axes turn with the velocity before it (MuJoCo's cdof_dot)
                for dof, axis in group:
                    a = _s_add(a, _s_add(_s_scale(_cross_motion(v, axis), qvel[dof]), _s_scale(axis, qacc[dof])))
                for dof, axis in group:
                    v = _s_add(v, _s_scale(axis, qvel[dof]))
            velocity[b], acceleration[b] = v, a
            force[b] = _s_add(inertias[b].apply(a), _cross_force(v, inertias[b].apply(v)))
        for b in reversed(self.bodies):
            parent = m.body_parentid[b]
            if parent:
                force[parent] = _s_add(force[parent], force[b])
        torque = [0.0] * self.nv
        for b in self.bodies:
            for dof, axis in _dofs(axes[b]):
                torque[dof] = _s_dot(axis, force[b])
        return _stack(torque, qvel)

    def rigid_body(self, qpos, qvel, ctrl) -> RigidBody:
        """The terms MJX's constraint stages read, generated (``RigidBody``)."""
        m = self.model
        position, rotation, axes = self.kinematics(qpos)
        inertias = self.inertias(position, rotation)
        moment = {0: _ZERO3, **{b: inertias[b].moment for b in self.bodies}}
        for b in reversed(self.bodies):
            moment[m.body_parentid[b]] = _v_add(moment[m.body_parentid[b]], moment[b])
        # MuJoCo's subtree centre of mass; a massless subtree keeps its body's inertial frame.
        subtree_com = {b: _v_scale(moment[b], 1.0 / float(m.body_subtreemass[b])) if m.body_subtreemass[b] >= mujoco.mjMINVAL
                       else _v_add(position[b], _mv(rotation[b], _constant(m.body_ipos[b]))) for b in moment}
        cdof = [None] * self.nv
        for b in self.bodies:
            centre = subtree_com[m.body_rootid[b]]
            for dof, (angular, linear) in _dofs(axes[b]):  # the same motion, its linear part taken at the centre
                cdof[dof] = angular + _v_add(linear, _cross(angular, centre))
        def frames(bodies, offsets, turns):  # of geoms or sites, fixed in their bodies
            return ([_v_add(position[b], _mv(rotation[b], _constant(offset))) for b, offset in zip(bodies, offsets)],
                    [_mm(rotation[b], _constant(_rotation(turn))) for b, turn in zip(bodies, turns)])

        geom_frames = frames(m.geom_bodyid, m.geom_pos, m.geom_quat)
        site_frames = frames(m.site_bodyid, m.site_pos, m.site_quat)
        placed = (axes, inertias)
        matrix = self.mass_matrix(placed, m.dof_armature)
        bias = self.inverse_dynamics(placed, qvel, [0.0] * self.nv)
        qfrc_smooth = self.applied_forces(qpos, qvel, ctrl) - bias
        qacc_smooth = _solve(matrix, qfrc_smooth)
        bodies = range(m.nbody)
        return RigidBody(
            xpos=_array([position[b] for b in bodies], qvel), xmat=_array([rotation[b] for b in bodies], qvel),
            geom_xpos=_frames_array(geom_frames[0], (0, 3), qvel), geom_xmat=_frames_array(geom_frames[1], (0, 3, 3), qvel),
            site_xpos=_frames_array(site_frames[0], (0, 3), qvel), site_xmat=_frames_array(site_frames[1], (0, 3, 3), qvel),
            subtree_com=_array([subtree_com[b] for b in bodies], qvel), cdof=_array(cdof, qvel),
            mass_matrix=_array(matrix, qvel), qfrc_smooth=qfrc_smooth, qacc_smooth=qacc_smooth)

    def mass_matrix(self, placed, diagonal=None):
        """Composite rigid bodies: M_ij = s_i . (I_c s_j) for dof i an ancestor of (or before, in its body) dof j;
        plus ``diagonal`` (constants per dof: armature, implicit damping), where given."""
        m = self.model
        axes, inertias = placed
        composite = dict(inertias)
        for b in reversed(self.bodies):
            parent = m.body_parentid[b]
            if parent:
                composite[parent] = composite[parent] + composite[b]
        motion = {dof: axis for b in self.bodies for dof, axis in _dofs(axes[b])}
        entries = [[0.0] * self.nv for _ in range(self.nv)]
        for b in self.bodies:
            for dof, axis in _dofs(axes[b]):
                force = composite[b].apply(axis)
                ancestor = dof
                while ancestor >= 0:
                    entries[ancestor][dof] = entries[dof][ancestor] = _s_dot(motion[ancestor], force)
                    ancestor = m.dof_parentid[ancestor]
        if diagonal is not None:
            for i in range(self.nv):
                entries[i][i] = _add(entries[i][i], float(diagonal[i]))
        return entries


def _skew(v):
    """[v]x of a [..., 3] array: [v]x u = v x u."""
    zero = jnp.zeros_like(v[..., 0])
    return jnp.stack([jnp.stack([zero, -v[..., 2], v[..., 1]], -1), jnp.stack([v[..., 2], zero, -v[..., 0]], -1),
                      jnp.stack([-v[..., 1], v[..., 0], zero], -1)], -2)


def _cross_motion_rows(velocity, motion):
    """Spatial motion cross products of [..., 6] rows (angular, linear)."""
    w, v, w2, v2 = velocity[..., :3], velocity[..., 3:], motion[..., :3], motion[..., 3:]
    return jnp.concatenate([jnp.cross(w, w2), jnp.cross(w, v2) + jnp.cross(v, w2)], -1)


def _cross_force_rows(velocity, force):
    w, v, n, f = velocity[..., :3], velocity[..., 3:], force[..., :3], force[..., 3:]
    return jnp.concatenate([jnp.cross(w, n) + jnp.cross(v, f), jnp.cross(w, f)], -1)


def _motion_row(angular, point):
    """The motion row of a rotation about ``angular`` through ``point`` (its linear part at the origin)."""
    return jnp.concatenate([angular, jnp.cross(point, angular)])


class _Arrays(_Scene):
    """The terms in array operations: kinematics body by body on 3-vectors and 3x3 matrices, everything
    after it over all bodies and dofs at once through constant masks of which dof moves what. Its traced
    program grows with the number of joints, not with their arithmetic."""

    def __init__(self, model: mujoco.MjModel):
        super().__init__(model)
        m = model
        lineage = [{0}]  # a body and its ancestors
        for b in self.bodies:
            lineage.append(lineage[m.body_parentid[b]] | {b})
        self.dof_body = np.asarray(m.dof_bodyid)
        # A dof's group turns together: a hinge or slide alone, a ball's three rotations, a free joint's
        # translations and its rotations; MuJoCo turns each group's axes with the velocity before it.
        group = np.zeros(self.nv, int)
        for j in range(m.njnt):
            first, width = m.jnt_dofadr[j], {FREE: 3, BALL: 3}.get(int(m.jnt_type[j]), 1)
            group[first:first + width] = j * 2
            if m.jnt_type[j] == FREE:
                group[first + 3:first + 6] = j * 2 + 1
        dofs, bodies = range(self.nv), range(model.nbody)
        # moves[b, d]: dof d moves body b; carries[d, e]: dof e moves what dof d's group hangs from;
        # subtree[b, c]: body c hangs from body b (or is b); chain[d, e]: d is e or on its dof_parentid path.
        self.moves = np.array([[self.dof_body[d] in lineage[b] for d in dofs] for b in bodies])
        self.carries = np.array([[self.dof_body[e] in lineage[self.dof_body[d]] and group[e] < group[d]
                                  for e in dofs] for d in dofs])
        self.subtree = np.array([[b in lineage[c] for c in bodies] for b in bodies])
        self.chain = np.zeros((self.nv, self.nv), bool)
        for e in dofs:
            d = e
            while d >= 0:
                self.chain[d, e], d = True, m.dof_parentid[d]
        self.inertial_frames = np.array([_rotation(q) for q in m.body_iquat]).reshape(-1, 3, 3)
        self.geom_frames = np.array([_rotation(q) for q in m.geom_quat]).reshape(-1, 3, 3)
        self.site_frames = np.array([_rotation(q) for q in m.site_quat]).reshape(-1, 3, 3)

    def kinematics(self, qpos):
        """Body frames [nbody, 3] and [nbody, 3, 3] (the world's first) and the joints' motion rows [nv, 6]."""
        m, like = self.model, lambda a: jnp.asarray(a, qpos.dtype)
        position, rotation, rows = [like(np.zeros(3))], [like(np.eye(3))], [None] * self.nv
        for b in self.bodies:
            parent = m.body_parentid[b]
            x = position[parent] + rotation[parent] @ like(m.body_pos[b])
            r = rotation[parent] @ like(_rotation(m.body_quat[b]))
            turning = []  # (first dof, anchor) of rotations about the body's final axes, as MuJoCo's cdof
            for j in self.joints[b]:
                address, dof, jpos = m.jnt_qposadr[j], m.jnt_dofadr[j], like(m.jnt_pos[j])
                if m.jnt_type[j] == FREE:  # a body of the world's: qpos holds its frame itself
                    x, r = qpos[address:address + 3], _array(_quaternion_rotation([qpos[address + 3 + i] for i in range(4)]), qpos)
                    rows[dof:dof + 3] = like(np.eye(6)[3:])
                    turning.append((dof + 3, x))
                    continue
                anchor = x + r @ jpos
                if m.jnt_type[j] == BALL:
                    r = r @ _array(_quaternion_rotation([qpos[address + i] for i in range(4)]), qpos)
                    x = anchor - r @ jpos
                    turning.append((dof, anchor))
                    continue
                axis = np.asarray(m.jnt_axis[j], float)
                world_axis = r @ like(axis)
                offset = qpos[address] - float(m.qpos0[address])
                if m.jnt_type[j] == SLIDE:
                    x = x + world_axis * offset
                    rows[dof] = jnp.concatenate([like(np.zeros(3)), world_axis])
                else:  # Rodrigues: c (1 - a a^T) + s [a]x + a a^T
                    r = r @ _array(_axis_rotation(_constant(axis), offset), qpos)
                    x = anchor - r @ jpos
                    rows[dof] = _motion_row(world_axis, anchor)
            for first, anchor in turning:
                rows[first:first + 3] = [_motion_row(column, anchor) for column in r.T]
            position.append(x)
            rotation.append(r)
        return jnp.stack(position), jnp.stack(rotation), jnp.stack(rows)

    def inertias(self, position, rotation):
        """Spatial inertias about the origin [nbody, 6, 6] (the world's zero), centres of mass and first moments."""
        m, like = self.model, lambda a: jnp.asarray(a, position.dtype)
        centre = position + jnp.einsum("bij,bj->bi", rotation, like(m.body_ipos))
        frame = rotation @ like(self.inertial_frames)
        about_centre = jnp.einsum("bij,bj,bkj->bik", frame, like(m.body_inertia), frame)
        mass = like(m.body_mass)[:, None, None]
        moment = mass[:, :, 0] * centre
        # Parallel axes: I_o = I_c + m (|c|^2 1 - c c^T).
        squared = jnp.sum(centre * centre, -1)[:, None, None]
        rotational = about_centre + mass * (squared * like(np.eye(3)) - centre[:, :, None] * centre[:, None, :])
        first = _skew(moment)  # the force (I w + h x v, m v - h x w) of a motion (w, v)
        spatial = jnp.concatenate([jnp.concatenate([rotational, first], -1),
                                   jnp.concatenate([-first, mass * like(np.eye(3))], -1)], -2)
        return spatial, centre, moment

    def place(self, qpos):
        """What the mass matrix and inverse dynamics share: the joints' motion rows and body inertias at ``qpos``."""
        position, rotation, motion = self.kinematics(qpos)
        return motion, self.inertias(position, rotation)[0]

    def inverse_dynamics(self, placed, qvel, qacc):
        """Recursive Newton-Euler over every body at once: M(q) qacc + c(q, qvel), armature excluded
        (MuJoCo's qfrc_bias at qacc)."""
        motion, inertia = placed
        like = lambda a: jnp.asarray(a, qvel.dtype)
        qacc = like(qacc)
        moving = motion * qvel[:, None]
        velocity = like(self.moves) @ moving
        turning = _cross_motion_rows(like(self.carries) @ moving, motion)  # cdof_dot: each axis turns with what carries it
        gravity = jnp.concatenate([like(np.zeros(3)), -like(self.gravity)])
        acceleration = gravity + like(self.moves) @ (turning * qvel[:, None] + motion * qacc[:, None])
        momentum = jnp.einsum("bij,bj->bi", inertia, velocity)
        force = jnp.einsum("bij,bj->bi", inertia, acceleration) + _cross_force_rows(velocity, momentum)
        return jnp.sum(motion * (like(self.subtree) @ force)[self.dof_body], -1)

    def mass_matrix(self, placed, diagonal=None):
        """Composite rigid bodies: M_de = s_d . (I_c s_e) for dof d on e's path to the root; plus ``diagonal``
        (constants per dof: armature, implicit damping), where given."""
        motion, inertia = placed
        composite = jnp.einsum("bc,cij->bij", jnp.asarray(self.subtree, inertia.dtype), inertia)
        force = jnp.einsum("dij,dj->di", composite[self.dof_body], motion)
        upper = jnp.where(self.chain, motion @ force.T, 0.0)
        matrix = upper + upper.T - jnp.diag(jnp.diag(upper))
        return matrix if diagonal is None else matrix + jnp.diag(jnp.asarray(diagonal, matrix.dtype))

    def rigid_body(self, qpos, qvel, ctrl) -> RigidBody:
        """The terms MJX's constraint stages read, generated (``RigidBody``)."""
        m, like = self.model, lambda a: jnp.asarray(a, qvel.dtype)
        position, rotation, motion = self.kinematics(qpos)
        inertia, centre, moment = self.inertias(position, rotation)
        # MuJoCo's subtree centre of mass; a massless subtree keeps its body's inertial frame.
        heavy = m.body_subtreemass >= mujoco.mjMINVAL
        subtree_com = jnp.where(heavy[:, None], like(self.subtree) @ moment
                                / like(np.where(heavy, m.body_subtreemass, 1.0))[:, None], centre)
        root_centre = subtree_com[m.body_rootid[self.dof_body]]  # cdof: the same motion, linear part at the centre
        cdof = jnp.concatenate([motion[:, :3], motion[:, 3:] + jnp.cross(motion[:, :3], root_centre)], -1)

        def frames(bodies, offsets, turns):  # of geoms or sites, fixed in their bodies
            return (position[bodies] + jnp.einsum("gij,gj->gi", rotation[bodies], like(offsets)),
                    rotation[bodies] @ like(turns))

        geom_xpos, geom_xmat = frames(m.geom_bodyid, m.geom_pos, self.geom_frames)
        site_xpos, site_xmat = frames(m.site_bodyid, m.site_pos, self.site_frames)
        placed = (motion, inertia)
        matrix = self.mass_matrix(placed, m.dof_armature)
        qfrc_smooth = self.applied_forces(qpos, qvel, ctrl) - self.inverse_dynamics(placed, qvel, [0.0] * self.nv)
        return RigidBody(xpos=position, xmat=rotation, geom_xpos=geom_xpos, geom_xmat=geom_xmat,
                         site_xpos=site_xpos, site_xmat=site_xmat,
                         subtree_com=subtree_com, cdof=cdof, mass_matrix=matrix, qfrc_smooth=qfrc_smooth,
                         qacc_smooth=_solve(matrix, qfrc_smooth))


def _dofs(groups):
    return [entry for group in groups for entry in group]


def _cholesky_solve(matrix, vector):
    """Solve a symmetric positive-definite system written out entry by entry (no loops, no LAPACK)."""
    n = len(vector)
    lower = [[0.0] * n for _ in range(n)]
    for j in range(n):
        lower[j][j] = _sqrt(_sub(matrix[j][j], _sum(_mul(lower[j][k], lower[j][k]) for k in range(j))))
        for i in range(j + 1, n):
            lower[i][j] = _div(_sub(matrix[i][j], _sum(_mul(lower[i][k], lower[j][k]) for k in range(j))), lower[j][j])
    forward = [0.0] * n
    for i in range(n):
        forward[i] = _div(_sub(vector[i], _sum(_mul(lower[i][k], forward[k]) for k in range(i))), lower[i][i])
    solution = [0.0] * n
    for i in reversed(range(n)):
        solution[i] = _div(_sub(forward[i], _sum(_mul(lower[k][i], solution[k]) for k in range(i + 1, n))), lower[i][i])
    return solution


def _solve(matrix, rhs):
    """``matrix``^-1 ``rhs`` (an array): written out entry by entry for a matrix of scalars (``_WrittenOut``'s),
    LAPACK's Cholesky solve for an array (``_Arrays``')."""
    if not isinstance(matrix, (list, tuple)):
        return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(matrix), rhs)
    return _stack(_cholesky_solve(matrix, [rhs[i] for i in range(len(matrix))]), rhs)


def _stack(scalars, like):
    return jnp.stack([jnp.full((), x, like.dtype) if isinstance(x, float) else x for x in scalars])


def _frames_array(nested, empty_shape, like):
    """``_array`` of a list of frames that may be empty (a model without geoms or sites)."""
    return _array(nested, like) if len(nested) else jnp.zeros(empty_shape, like.dtype)


def _array(nested, like):
    """Nested sequences of scalars (constants or traced) as one array of ``like``'s dtype."""
    if isinstance(nested[0], (tuple, list)):
        return jnp.stack([_array(item, like) for item in nested])
    return _stack(nested, like)


def make_scene(model: mujoco.MjModel) -> _Scene:
    """The rigid-body terms of ``model`` in the form that pays for its size on this backend (``WRITTEN_OUT_DOFS``)."""
    written_out = WRITTEN_OUT_DOFS.get(jax.default_backend(), WRITTEN_OUT_DOFS["gpu"])
    return (_WrittenOut if model.nv <= written_out else _Arrays)(model)


def make_rigid_body(model: mujoco.MjModel) -> Callable:
    """``rigid_body(qpos, qvel, ctrl) -> RigidBody`` of one example, differentiated by plain autodiff."""
    return make_scene(model).rigid_body


def make_acceleration(model: mujoco.MjModel) -> Callable:
    """``acceleration(qpos, qvel, ctrl) -> qacc`` of one example, with the inverse-dynamics derivative."""
    scene = make_scene(model)

    def solve(placed, rhs):
        return _solve(scene.mass_matrix(placed, scene.diagonal), rhs)

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
