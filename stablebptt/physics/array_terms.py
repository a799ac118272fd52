"""The rigid-body terms in arrays (``ArrayTerms``): kinematics body by body on 3-vectors and 3x3
matrices, then everything else as one array operation over all bodies and dofs through constant
masks of which dof moves which body. Its program grows with the number of joints, not with their
arithmetic."""
from __future__ import annotations

import jax.numpy as jnp
import mujoco
import numpy as np

from stablebptt.physics.folding import as_array, as_constant, axis_rotation, quaternion_rotation, solve_spd
from stablebptt.physics.scene_terms import BALL, FREE, SLIDE, RigidBody, SceneTerms, rotation_matrix, subtree_mask


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


class ArrayTerms(SceneTerms):
    """The terms in array operations: kinematics body by body on 3-vectors and 3x3 matrices, everything
    after it over all bodies and dofs at once through constant masks of which dof moves what. Its traced
    program grows with the number of joints, not with their arithmetic."""

    def __init__(self, model: mujoco.MjModel):
        super().__init__(model)
        m = model
        self.dof_body = np.asarray(m.dof_bodyid)
        # A dof's group turns together: a hinge or slide alone, a ball's three rotations, a free joint's
        # translations and its rotations; MuJoCo turns each group's axes with the velocity before it.
        group = np.zeros(self.nv, int)
        for j in range(m.njnt):
            first, width = m.jnt_dofadr[j], {FREE: 3, BALL: 3}.get(int(m.jnt_type[j]), 1)
            group[first:first + width] = j * 2
            if m.jnt_type[j] == FREE:
                group[first + 3:first + 6] = j * 2 + 1
        dofs = range(self.nv)
        # subtree[b, c]: body c hangs from body b (or is b); moves[b, d]: dof d moves body b; carries[d, e]:
        # dof e moves what dof d's group hangs from; chain[d, e]: d is e or on its dof_parentid path.
        self.subtree = subtree_mask(m.body_parentid)
        self.moves = self.subtree[self.dof_body].T
        self.carries = self.subtree[self.dof_body][:, self.dof_body].T & (group[None, :] < group[:, None])
        self.chain = np.zeros((self.nv, self.nv), bool)
        for e in dofs:
            d = e
            while d >= 0:
                self.chain[d, e], d = True, m.dof_parentid[d]
        self.inertial_frames = np.array([rotation_matrix(q) for q in m.body_iquat]).reshape(-1, 3, 3)
        self.geom_frames = np.array([rotation_matrix(q) for q in m.geom_quat]).reshape(-1, 3, 3)
        self.site_frames = np.array([rotation_matrix(q) for q in m.site_quat]).reshape(-1, 3, 3)

    def kinematics(self, qpos):
        """Body frames [nbody, 3] and [nbody, 3, 3] (the world's first) and the joints' motion rows [nv, 6]."""
        m, like = self.model, lambda a: jnp.asarray(a, qpos.dtype)
        position, rotation, rows = [like(np.zeros(3))], [like(np.eye(3))], [None] * self.nv
        for b in self.bodies:
            parent = m.body_parentid[b]
            x = position[parent] + rotation[parent] @ like(m.body_pos[b])
            r = rotation[parent] @ like(rotation_matrix(m.body_quat[b]))
            turning = []  # (first dof, anchor) of rotations about the body's final axes, as MuJoCo's cdof
            for j in self.joints[b]:
                address, dof, jpos = m.jnt_qposadr[j], m.jnt_dofadr[j], like(m.jnt_pos[j])
                if m.jnt_type[j] == FREE:  # a body of the world's: qpos holds its frame itself
                    x, r = qpos[address:address + 3], as_array(quaternion_rotation([qpos[address + 3 + i] for i in range(4)]), qpos)
                    rows[dof:dof + 3] = like(np.eye(6)[3:])
                    turning.append((dof + 3, x))
                    continue
                anchor = x + r @ jpos
                if m.jnt_type[j] == BALL:
                    r = r @ as_array(quaternion_rotation([qpos[address + i] for i in range(4)]), qpos)
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
                    r = r @ as_array(axis_rotation(as_constant(axis), offset), qpos)
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
                         qacc_smooth=solve_spd(matrix, qfrc_smooth))
