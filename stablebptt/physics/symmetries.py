"""Columns of a step's state Jacobian that a scene's symmetries fix: translation and Galilean boost.

Forward-mode step derivatives push no tangent through the simulator for them
(``dynamics.KnownColumns``); ``symmetries(model, effects)`` finds them from the
model's structure alone.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import mujoco
import numpy as np

from stablebptt.flows.dynamics import KnownColumns

if TYPE_CHECKING:
    from stablebptt.physics.effects import SceneEffects

_SLIDE, _FREE = int(mujoco.mjtJoint.mjJNT_SLIDE), int(mujoco.mjtJoint.mjJNT_FREE)


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

