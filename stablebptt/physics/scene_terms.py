"""A kinematic tree's numbers, read once from the model, and what both forms of its terms share:
the joints' types, actuator transmissions, springs, dampers and actuators (``SceneTerms``), the
terms in MuJoCo's frames (``RigidBody``)."""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from stablebptt.physics.folding import ZERO3, as_constant

_DISABLE = mujoco.mjtDisableBit
FREE, BALL = int(mujoco.mjtJoint.mjJNT_FREE), int(mujoco.mjtJoint.mjJNT_BALL)
SLIDE, HINGE = int(mujoco.mjtJoint.mjJNT_SLIDE), int(mujoco.mjtJoint.mjJNT_HINGE)
EULER, RK4 = int(mujoco.mjtIntegrator.mjINT_EULER), int(mujoco.mjtIntegrator.mjINT_RK4)

def subtree_mask(parents: np.ndarray) -> np.ndarray:
    """``mask[b, c]``: body ``c`` hangs from body ``b`` or is ``b`` (the world, body 0, above every body);
    ``parents`` MuJoCo's ``body_parentid``, parents before their children."""
    mask = np.eye(len(parents), dtype=bool)
    for body in range(1, len(parents)):
        mask[:, body] |= mask[:, parents[body]]
    return mask


def joints_pulled(model: mujoco.MjModel, actuator: int) -> list[tuple[int, float]] | None:
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
        pulled, gear = joints_pulled(model, actuator), float(model.actuator_gear[actuator, 0])
        if pulled is None:
            raise ValueError("an actuator pulls neither a joint nor a fixed tendon (tree.unsupported)")
        for joint, coefficient in pulled:
            length[actuator, model.jnt_qposadr[joint]] += gear * coefficient
            moment[actuator, model.jnt_dofadr[joint]] += gear * coefficient
    return length, moment


def rotation_matrix(quat: np.ndarray) -> np.ndarray:
    matrix = np.zeros(9)
    mujoco.mju_quat2Mat(matrix, np.asarray(quat, dtype=float))
    return matrix.reshape(3, 3)

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


class SceneTerms:
    """The model's numbers, read once; its bodies in MuJoCo's order (parents first). The rigid-body terms
    come in two forms of the same physics (``make_scene`` picks one): ``_WrittenOut`` and ``_Arrays``."""

    def __init__(self, model: mujoco.MjModel):
        self.model = model
        self.nv = model.nv
        disabled = lambda bit: bool(model.opt.disableflags & bit)
        self.gravity = ZERO3 if disabled(_DISABLE.mjDSBL_GRAVITY) else as_constant(model.opt.gravity)
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
