"""A step generated per scene for small kinematic trees of hinge and slide joints.

MJX runs every stage over all bodies at once: scans over tree levels, gathers
of parents, a sparse mass-matrix factorisation. For a tree of a few bodies that
is many tiny dependent operations per step (on a GPU, many tiny kernels) and,
differentiated, a program XLA takes long to compile. Here the rigid-body
recursions are written out body by body while tracing, with the model's numbers
as constants: what remains is straight-line arithmetic on each example's
scalars, which XLA fuses into few kernels.

The physics is MuJoCo's, term by term (tests compare with ``mujoco.mj_step`` in
float64): forward kinematics, the composite-rigid-body mass matrix plus
armature, recursive Newton-Euler bias forces with gravity, springs and dampers,
joint-transmission actuators (fixed gain, affine bias, control and force
clamps), and the Euler (with its implicit joint damping) or RK4 integrator.
Spatial vectors are (angular, linear) about the world origin.

A contact-free scene's derivative is the inverse-dynamics one
(``scene.implicit_derivative_applies`` explains it): the acceleration solves
M~(q) qacc = f(q, qvel, ctrl), so d qacc = -M~^-1 d(ID(q, qvel, qacc) - f) at
fixed qacc, and the mass matrix, its factorisation and the solve are never
differentiated. A scene with contacts, joint limits or friction loss takes the
generated terms in MuJoCo's frames (``RigidBody``) into MJX's collision,
constraint rows and solver (``lean_step``).
"""
from __future__ import annotations

import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from stablebptt import integrators

_DISABLE = mujoco.mjtDisableBit
HINGE, SLIDE = int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)
EULER, RK4 = int(mujoco.mjtIntegrator.mjINT_EULER), int(mujoco.mjtIntegrator.mjINT_RK4)
MAX_DOFS = 12  # the unrolled factorisation grows as nv^3 in traced operations


def unsupported(model: mujoco.MjModel, effects) -> str:
    """Why the generated step does not cover ``model`` ('' when it does); ``effects`` from ``scene.analyze``.

    Contacts, joint limits and friction loss are MJX's own stages fed the generated terms; equality
    constraints (some read site frames and body orientations, which are not generated) and tendons
    are left to MJX's stages.
    """
    present = [name for name in ("equality", "tendons", "activation", "gravity_compensation", "fluid")
               if getattr(effects, name)]
    if present:
        return "equality constraints" if present[0] == "equality" else present[0].replace("_", " ")
    if model.nv == 0 or model.nv > MAX_DOFS:
        return f"{model.nv} degrees of freedom (covered: 1 to {MAX_DOFS})"
    if not np.all(np.isin(model.jnt_type, (HINGE, SLIDE))):
        return "free or ball joints"
    if int(model.opt.integrator) not in (EULER, RK4):
        return f"the {mujoco.mjtIntegrator(model.opt.integrator).name} integrator"
    if model.opt.enableflags:
        return "enabled optional features"
    nonlinear = [model.dof_dampingpoly, model.jnt_stiffnesspoly, model.jnt_springyield,
                 model.actuator_dampingpoly, model.jnt_actgravcomp]
    if any(np.any(np.asarray(a) != 0) for a in nonlinear) or np.any(model.jnt_plasticadr >= 0):
        return "nonlinear or plastic springs and dampers"
    if model.nu and not (np.all(model.actuator_trntype == int(mujoco.mjtTrn.mjTRN_JOINT))
                         and np.all(model.actuator_dyntype == int(mujoco.mjtDyn.mjDYN_NONE))
                         and np.all(model.actuator_gaintype == int(mujoco.mjtGain.mjGAIN_FIXED))
                         and np.all(np.isin(model.actuator_biastype, (int(mujoco.mjtBias.mjBIAS_NONE),
                                                                      int(mujoco.mjtBias.mjBIAS_AFFINE))))):
        return "actuators other than fixed-gain joint actuators"
    return ""


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
    subtree_com: jax.Array  # [nbody, 3]
    cdof: jax.Array  # [nv, 6] joint motion axes about their tree's centre of mass
    mass_matrix: jax.Array  # [nv, nv] armature included (not Euler's implicit damping)
    qfrc_smooth: jax.Array  # [nv] springs, dampers and actuators less the bias forces
    qacc_smooth: jax.Array  # [nv] the acceleration without constraints


class _Scene:
    """The model's numbers, read once; its bodies in MuJoCo's order (parents first)."""

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
        self.bodies = list(range(1, model.nbody))
        self.joints = {b: list(range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b]))
                       for b in self.bodies}

    def kinematics(self, qpos):
        """Per body: position, rotation, and its joints' motion axes [(dof, (angular, linear))]."""
        m = self.model
        position, rotation, axes = {0: _ZERO3}, {0: _IDENTITY}, {}
        for b in self.bodies:
            parent = m.body_parentid[b]
            x = _v_add(position[parent], _mv(rotation[parent], _constant(m.body_pos[b])))
            r = _mm(rotation[parent], _constant(_rotation(m.body_quat[b])))
            axes[b] = []
            for j in self.joints[b]:
                axis = _constant(m.jnt_axis[j])
                world_axis = _mv(r, axis)
                address = m.jnt_qposadr[j]
                offset = qpos[address] - float(m.qpos0[address])
                if m.jnt_type[j] == SLIDE:
                    x = _v_add(x, _v_scale(world_axis, offset))
                    axes[b].append((m.jnt_dofadr[j], (_ZERO3, world_axis)))
                else:
                    anchor = _v_add(x, _mv(r, _constant(m.jnt_pos[j])))
                    r = _mm(r, _axis_rotation(axis, offset))
                    x = _v_sub(anchor, _mv(r, _constant(m.jnt_pos[j])))
                    axes[b].append((m.jnt_dofadr[j], (world_axis, _cross(anchor, world_axis))))
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
            for dof, axis in axes[b]:
                a = _s_add(a, _s_add(_s_scale(_cross_motion(v, axis), qvel[dof]), _s_scale(axis, qacc[dof])))
                v = _s_add(v, _s_scale(axis, qvel[dof]))
            velocity[b], acceleration[b] = v, a
            force[b] = _s_add(inertias[b].apply(a), _cross_force(v, inertias[b].apply(v)))
        for b in reversed(self.bodies):
            parent = m.body_parentid[b]
            if parent:
                force[parent] = _s_add(force[parent], force[b])
        torque = [0.0] * self.nv
        for b in self.bodies:
            for dof, axis in axes[b]:
                torque[dof] = _s_dot(axis, force[b])
        return torque

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
            for dof, (angular, linear) in axes[b]:  # the same motion, its linear part taken at the centre
                cdof[dof] = angular + _v_add(linear, _cross(angular, centre))
        geom_frames = [(_v_add(position[b], _mv(rotation[b], _constant(m.geom_pos[g]))),
                        _mm(rotation[b], _constant(_rotation(m.geom_quat[g])))) for g, b in enumerate(m.geom_bodyid)]
        placed = (axes, inertias)
        matrix = self.mass_matrix(placed, m.dof_armature)
        bias = _stack(self.inverse_dynamics(placed, qvel, [0.0] * self.nv), qvel)
        qfrc_smooth = self.applied_forces(qpos, qvel, ctrl) - bias
        qacc_smooth = _solve(matrix, qfrc_smooth)
        bodies = range(m.nbody)
        return RigidBody(
            xpos=_array([position[b] for b in bodies], qvel), xmat=_array([rotation[b] for b in bodies], qvel),
            geom_xpos=_array([p for p, _ in geom_frames], qvel), geom_xmat=_array([r for _, r in geom_frames], qvel),
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
        motion = {dof: axis for b in self.bodies for dof, axis in axes[b]}
        entries = [[0.0] * self.nv for _ in range(self.nv)]
        for b in self.bodies:
            for dof, axis in axes[b]:
                force = composite[b].apply(axis)
                ancestor = dof
                while ancestor >= 0:
                    entries[ancestor][dof] = entries[dof][ancestor] = _s_dot(motion[ancestor], force)
                    ancestor = m.dof_parentid[ancestor]
        if diagonal is not None:
            for i in range(self.nv):
                entries[i][i] = _add(entries[i][i], float(diagonal[i]))
        return entries

    def applied_forces(self, qpos, qvel, ctrl):
        """Springs, dampers and actuators: MuJoCo's qfrc_passive + qfrc_actuator."""
        m = self.model
        force = jnp.zeros(self.nv, dtype=qvel.dtype)
        if self.dampers:
            force = force - jnp.asarray(m.dof_damping) * qvel
        if self.springs and np.any(m.jnt_stiffness):
            dofs, addresses = m.jnt_dofadr, m.jnt_qposadr
            force = force.at[dofs].add(-jnp.asarray(m.jnt_stiffness) * (qpos[addresses] - m.qpos_spring[addresses]))
        if self.actuation:
            if self.clamp_ctrl and np.any(m.actuator_ctrllimited):
                limited = np.asarray(m.actuator_ctrllimited, bool)
                low, high = m.actuator_ctrlrange[:, 0], m.actuator_ctrlrange[:, 1]
                ctrl = jnp.where(limited, jnp.clip(ctrl, low, high), ctrl)
            joint = m.actuator_trnid[:, 0]
            gear = jnp.asarray(m.actuator_gear[:, 0])
            length = gear * qpos[m.jnt_qposadr[joint]]
            velocity = gear * qvel[m.jnt_dofadr[joint]]
            bias = np.asarray(m.actuator_biasprm)
            actuator = jnp.asarray(m.actuator_gainprm[:, 0]) * ctrl + (
                bias[:, 0] + bias[:, 1] * length + bias[:, 2] * velocity)
            if np.any(m.actuator_forcelimited):
                limited = np.asarray(m.actuator_forcelimited, bool)
                actuator = jnp.where(limited, jnp.clip(actuator, m.actuator_forcerange[:, 0],
                                                       m.actuator_forcerange[:, 1]), actuator)
            generalized = jnp.zeros(self.nv, dtype=qvel.dtype).at[m.jnt_dofadr[joint]].add(gear * actuator)
            if np.any(m.jnt_actfrclimited):
                limited = np.asarray(m.jnt_actfrclimited, bool)
                dofs = m.jnt_dofadr[limited]
                generalized = generalized.at[dofs].set(jnp.clip(generalized[dofs], m.jnt_actfrcrange[limited, 0],
                                                                m.jnt_actfrcrange[limited, 1]))
            force = force + generalized
        return force


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
    """``matrix``^-1 ``rhs`` (an array) by the written-out Cholesky solve, as an array."""
    return _stack(_cholesky_solve(matrix, [rhs[i] for i in range(len(matrix))]), rhs)


def _stack(scalars, like):
    return jnp.stack([jnp.full((), x, like.dtype) if isinstance(x, float) else x for x in scalars])


def _array(nested, like):
    """Nested sequences of scalars (constants or traced) as one array of ``like``'s dtype."""
    if isinstance(nested[0], (tuple, list)):
        return jnp.stack([_array(item, like) for item in nested])
    return _stack(nested, like)


def make_rigid_body(model: mujoco.MjModel) -> Callable:
    """``rigid_body(qpos, qvel, ctrl) -> RigidBody`` of one example, differentiated by plain autodiff."""
    return _Scene(model).rigid_body


def make_acceleration(model: mujoco.MjModel) -> Callable:
    """``acceleration(qpos, qvel, ctrl) -> qacc`` of one example, with the inverse-dynamics derivative."""
    scene = _Scene(model)

    def solve(placed, rhs):
        return _solve(scene.mass_matrix(placed, scene.diagonal), rhs)

    def residual(qpos, qvel, ctrl, qacc, placed):
        return _stack(scene.inverse_dynamics(placed, qvel, qacc), qvel) - scene.applied_forces(qpos, qvel, ctrl)

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
