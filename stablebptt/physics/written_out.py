"""The rigid-body terms written out scalar by scalar, the model's zeros folded away while tracing
(``WrittenOut``): straight-line arithmetic on each example's scalars, which XLA fuses into few kernels."""
from __future__ import annotations

import mujoco

from stablebptt.physics.folding import (
    IDENTITY,
    ZERO3,
    add,
    as_array,
    as_constant,
    axis_rotation,
    cross,
    dot,
    frames_as_array,
    mm,
    mul,
    mv,
    quaternion_rotation,
    solve_spd,
    stack_scalars,
    sub,
    transpose,
    v_add,
    v_scale,
    v_scale_each,
    v_sub,
)
from stablebptt.physics.scene_terms import BALL, FREE, SLIDE, RigidBody, SceneTerms, rotation_matrix


class _Inertia:
    """A spatial inertia about the origin: rotational part, first moment m c, mass (they add)."""

    def __init__(self, rotational, moment, mass):
        self.rotational, self.moment, self.mass = rotational, moment, mass

    def __add__(self, other):
        return _Inertia(tuple(v_add(a, b) for a, b in zip(self.rotational, other.rotational)),
                        v_add(self.moment, other.moment), self.mass + other.mass)

    def apply(self, motion):
        angular, linear = motion
        return (v_add(mv(self.rotational, angular), cross(self.moment, linear)),
                v_sub(v_scale(linear, self.mass), cross(self.moment, angular)))


def _cross_motion(velocity, motion):
    (w, v), (w2, v2) = velocity, motion
    return cross(w, w2), v_add(cross(w, v2), cross(v, w2))


def _cross_force(velocity, force):
    (w, v), (n, f) = velocity, force
    return v_add(cross(w, n), cross(v, f)), cross(w, f)


def _s_dot(motion, force):
    return add(dot(motion[0], force[0]), dot(motion[1], force[1]))


def _s_add(a, b):
    return v_add(a[0], b[0]), v_add(a[1], b[1])


def _s_scale(motion, factor):
    return v_scale(motion[0], factor), v_scale(motion[1], factor)

class WrittenOut(SceneTerms):
    """The terms written out scalar by scalar, the model's zeros folded away while tracing."""

    def kinematics(self, qpos):
        """Per body: position, rotation, and its joints' motion axes as groups [[(dof, (angular, linear))]].

        A group's axes move together: a hinge or slide is a group of one, a ball joint's (or a free
        joint's) three rotations are one group about the body's final axes, as MuJoCo's ``cdof`` has them.
        """
        m = self.model
        position, rotation, axes = {0: ZERO3}, {0: IDENTITY}, {}
        for b in self.bodies:
            parent = m.body_parentid[b]
            x = v_add(position[parent], mv(rotation[parent], as_constant(m.body_pos[b])))
            r = mm(rotation[parent], as_constant(rotation_matrix(m.body_quat[b])))
            axes[b], turning = [], []  # turning: (group, first dof, anchor) of rotations about the final axes
            for j in self.joints[b]:
                address, dof = m.jnt_qposadr[j], m.jnt_dofadr[j]
                if m.jnt_type[j] == FREE:  # a body of the world's: qpos holds its frame itself
                    x = tuple(qpos[address + i] for i in range(3))
                    r = quaternion_rotation([qpos[address + 3 + i] for i in range(4)])
                    axes[b] += [[(dof + i, (ZERO3, IDENTITY[i])) for i in range(3)], []]
                    turning.append((axes[b][-1], dof + 3, x))
                    continue
                if m.jnt_type[j] == BALL:
                    anchor = v_add(x, mv(r, as_constant(m.jnt_pos[j])))
                    r = mm(r, quaternion_rotation([qpos[address + i] for i in range(4)]))
                    x = v_sub(anchor, mv(r, as_constant(m.jnt_pos[j])))
                    axes[b].append([])
                    turning.append((axes[b][-1], dof, anchor))
                    continue
                axis = as_constant(m.jnt_axis[j])
                world_axis = mv(r, axis)
                offset = qpos[address] - float(m.qpos0[address])
                if m.jnt_type[j] == SLIDE:
                    x = v_add(x, v_scale(world_axis, offset))
                    axes[b].append([(dof, (ZERO3, world_axis))])
                else:
                    anchor = v_add(x, mv(r, as_constant(m.jnt_pos[j])))
                    r = mm(r, axis_rotation(axis, offset))
                    x = v_sub(anchor, mv(r, as_constant(m.jnt_pos[j])))
                    axes[b].append([(dof, (world_axis, cross(anchor, world_axis)))])
            columns = transpose(r)
            for group, first, anchor in turning:
                group += [(first + i, (columns[i], cross(anchor, columns[i]))) for i in range(3)]
            position[b], rotation[b] = x, r
        return position, rotation, axes

    def inertias(self, position, rotation):
        m = self.model
        inertias = {}
        for b in self.bodies:
            centre = v_add(position[b], mv(rotation[b], as_constant(m.body_ipos[b])))
            frame = mm(rotation[b], as_constant(rotation_matrix(m.body_iquat[b])))
            principal = as_constant(m.body_inertia[b])
            about_centre = mm(tuple(v_scale_each(row, principal) for row in frame), transpose(frame))
            mass = float(m.body_mass[b])
            # Parallel axes: I_o = I_c + m (|c|^2 1 - c c^T).
            squared = dot(centre, centre)
            rotational = tuple(tuple(add(about_centre[i][j], mul(mass, sub(squared if i == j else 0.0,
                                                                              mul(centre[i], centre[j]))))
                                     for j in range(3)) for i in range(3))
            inertias[b] = _Inertia(rotational, v_scale(centre, mass), mass)
        return inertias

    def place(self, qpos):
        """What the mass matrix and inverse dynamics share: joint axes and body inertias at ``qpos``."""
        position, rotation, axes = self.kinematics(qpos)
        return axes, self.inertias(position, rotation)

    def inverse_dynamics(self, placed, qvel, qacc):
        """Recursive Newton-Euler: M(q) qacc + c(q, qvel), armature excluded (MuJoCo's qfrc_bias at qacc)."""
        m = self.model
        axes, inertias = placed
        velocity, acceleration, force = {0: (ZERO3, ZERO3)}, {0: (ZERO3, v_scale(self.gravity, -1.0))}, {}
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
        return stack_scalars(torque, qvel)

    def rigid_body(self, qpos, qvel, ctrl) -> RigidBody:
        """The terms MJX's constraint stages read, generated (``RigidBody``)."""
        m = self.model
        position, rotation, axes = self.kinematics(qpos)
        inertias = self.inertias(position, rotation)
        moment = {0: ZERO3, **{b: inertias[b].moment for b in self.bodies}}
        for b in reversed(self.bodies):
            moment[m.body_parentid[b]] = v_add(moment[m.body_parentid[b]], moment[b])
        # MuJoCo's subtree centre of mass; a massless subtree keeps its body's inertial frame.
        subtree_com = {b: v_scale(moment[b], 1.0 / float(m.body_subtreemass[b])) if m.body_subtreemass[b] >= mujoco.mjMINVAL
                       else v_add(position[b], mv(rotation[b], as_constant(m.body_ipos[b]))) for b in moment}
        cdof = [None] * self.nv
        for b in self.bodies:
            centre = subtree_com[m.body_rootid[b]]
            for dof, (angular, linear) in _dofs(axes[b]):  # the same motion, its linear part taken at the centre
                cdof[dof] = angular + v_add(linear, cross(angular, centre))
        def frames(bodies, offsets, turns):  # of geoms or sites, fixed in their bodies
            return ([v_add(position[b], mv(rotation[b], as_constant(offset))) for b, offset in zip(bodies, offsets)],
                    [mm(rotation[b], as_constant(rotation_matrix(turn))) for b, turn in zip(bodies, turns)])

        geom_frames = frames(m.geom_bodyid, m.geom_pos, m.geom_quat)
        site_frames = frames(m.site_bodyid, m.site_pos, m.site_quat)
        placed = (axes, inertias)
        matrix = self.mass_matrix(placed, m.dof_armature)
        bias = self.inverse_dynamics(placed, qvel, [0.0] * self.nv)
        qfrc_smooth = self.applied_forces(qpos, qvel, ctrl) - bias
        qacc_smooth = solve_spd(matrix, qfrc_smooth)
        bodies = range(m.nbody)
        return RigidBody(
            xpos=as_array([position[b] for b in bodies], qvel), xmat=as_array([rotation[b] for b in bodies], qvel),
            geom_xpos=frames_as_array(geom_frames[0], (0, 3), qvel), geom_xmat=frames_as_array(geom_frames[1], (0, 3, 3), qvel),
            site_xpos=frames_as_array(site_frames[0], (0, 3), qvel), site_xmat=frames_as_array(site_frames[1], (0, 3, 3), qvel),
            subtree_com=as_array([subtree_com[b] for b in bodies], qvel), cdof=as_array(cdof, qvel),
            mass_matrix=as_array(matrix, qvel), qfrc_smooth=qfrc_smooth, qacc_smooth=qacc_smooth)

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
                entries[i][i] = add(entries[i][i], float(diagonal[i]))
        return entries

def _dofs(groups):
    return [entry for group in groups for entry in group]
