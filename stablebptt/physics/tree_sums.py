"""Sums over the tree of MJX's position and velocity stages, differentiated as constant products.

MJX's ``smooth.com_pos`` and ``smooth.crb`` sum masses and inertias over subtrees by scanning the tree
from its leaves, level by level, and pick each dof's root, joint and body by gathers; ``smooth.com_vel``
sums the dofs' motions down the tree into the bodies' velocities and ``smooth.rne`` their accelerations
down it and their forces up it; ``smooth.subtree_vel`` (the subtree sensors') sums momenta up it. Their
reverse passes run those scans backwards with the transposes of every gather and scatter. The same sums
are a constant 0/1 matrix (which bodies hang from which, which dofs move which) times the rows summed,
and each pick is a one-hot matrix times the rows it picks from: ``REMEDIES`` give MJX's functions the
derivative of that form while their values stay MJX's own, bit for bit.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from stablebptt.physics.mjx_internals import mjx, mjx_math, smooth, support, types
from stablebptt.physics.scene_terms import BALL, FREE, SLIDE
from stablebptt.physics.tree_maps import Structure, dof_subtrees, joints_moved, picks, root, structure, subtree
from stablebptt.physics.values_kept import times, values_kept

class _Rows(NamedTuple):
    """A tree's constant 0/1 maps for sums over subtrees and picks of rows."""
    subtree: np.ndarray      # (nbody, nbody): body c hangs from body b or is b
    root: np.ndarray         # (nbody, nbody): b's tree's root
    dof_body: np.ndarray     # (nv, nbody)
    dof_root: np.ndarray     # (nv, nbody)
    dof_joint: np.ndarray    # (nv, njnt)
    along_joint: np.ndarray  # (nv, 1): the dof turns about (hinge) or moves along (slide) its joint's axis
    slide: np.ndarray        # (nv, 1)
    column: np.ndarray       # (3, nv, 1): the dof turns about its body's frame's axis k (ball, free)
    translation: np.ndarray  # (nv, 3): a free joint's translation dofs' constant motion axes
    moved_before: np.ndarray  # (nv, nv): dof i moves dof j's frame (a body above, an earlier joint on its body,
                              # or a free joint's translation before its turns)
    parent: np.ndarray       # (nbody, nbody): b's parent (the world its own)
    below: np.ndarray        # (nbody, nbody): body c hangs from body b, b itself not counted
    off_world: np.ndarray    # (nbody, 1): every body but the world


@functools.lru_cache(maxsize=64)
def _rows(tree: Structure) -> _Rows:
    dof_bodies, dof_joints = tree.dof_bodies, tree.dof_joints
    nbody, nv = len(tree.parents), len(dof_bodies)
    kinds = np.asarray(tree.joint_types, int)[list(dof_joints)]
    # A dof's place within its joint: a free joint's dofs are 3 translations, then 3 turns; a ball's 3 turns.
    place = np.array([dof - dof_joints.index(joint) for dof, joint in enumerate(dof_joints)], int)
    turn = np.where(kinds == FREE, place - 3, np.where(kinds == BALL, place, -1))
    column = np.stack([(turn == k).astype(np.float32)[:, None] for k in range(3)])
    translation = np.zeros((nv, 3), np.float32)
    moving = (kinds == FREE) & (place < 3)
    translation[np.nonzero(moving)[0], place[moving]] = 1.0
    along = ~np.isin(kinds, (FREE, BALL))
    joints = np.asarray(dof_joints, int)
    moved_before = joints_moved(tree)[joints][:, joints] | (
        (joints[:, None] == joints[None, :]) & (kinds == FREE)[:, None] & (place[:, None] < 3) & (place[None, :] >= 3))
    within = subtree(tree).astype(np.float32)
    off_world = np.ones((nbody, 1), np.float32)
    off_world[0] = 0.0
    return _Rows(within, root(tree), picks(dof_bodies, nbody),
                 picks([tree.roots[body] for body in dof_bodies], nbody), picks(dof_joints, len(tree.joint_types)),
                 along.astype(np.float32)[:, None], (kinds == SLIDE).astype(np.float32)[:, None], column, translation,
                 moved_before.astype(np.float32), picks(tree.parents, nbody), within - np.eye(nbody, dtype=np.float32),
                 off_world)


def _rows_of(model: mjx.Model) -> _Rows:
    return _rows(structure(model))


def _com_pos_as_products(model: mjx.Model, data: mjx.Data) -> tuple:
    """``smooth.com_pos``'s subtree centres of mass, inertias about them and motion axes, its sums and picks
    as products."""
    rows = _rows_of(model)
    mass = model.body_mass[:, None]
    weighted, total = times(rows.subtree, data.xipos * mass), times(rows.subtree, mass)
    subtree_com = jnp.where(total < mujoco.mjMINVAL, data.xipos, weighted / jnp.maximum(total, mujoco.mjMINVAL))
    offset = data.xipos - times(rows.root, subtree_com)
    rotated = jnp.einsum("bij,bj,bkj->bik", data.ximat, model.body_inertia, data.ximat)
    parallel_axis = (jnp.sum(offset * offset, -1)[:, None, None] * jnp.eye(3, dtype=offset.dtype)
                     - offset[:, :, None] * offset[:, None, :])
    inertia = rotated + parallel_axis * mass[:, :, None]
    upper = jnp.stack([inertia[:, i, j] for i, j in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))], -1)
    cinert = jnp.concatenate([upper, offset * mass, mass], -1)
    frames = times(rows.dof_body, data.xmat)  # one product for the three columns: one transpose in reverse mode
    axis = rows.along_joint * times(rows.dof_joint, data.xaxis) + sum(rows.column[k] * frames[:, :, k]
                                                                      for k in range(3))
    arm = times(rows.dof_root, subtree_com) - times(rows.dof_joint, data.xanchor)
    turning = 1.0 - rows.slide
    cdof = jnp.concatenate([axis * turning, jnp.cross(axis, arm) * turning + axis * rows.slide
                            + jnp.asarray(rows.translation, axis.dtype)], -1)
    return subtree_com, cinert, cdof


def _crb_as_products(model: mjx.Model, data: mjx.Data) -> tuple:
    """``smooth.crb``'s composite inertias and mass matrix, its subtree sums and picks as products."""
    rows = _rows_of(model)
    composite = times(rows.subtree, data._impl.cinert).at[0].set(0.0)
    cdof_force = jax.vmap(mjx_math.inert_mul)(times(rows.dof_body, composite), data.cdof)
    return composite, support.make_m(model, cdof_force, data.cdof, model.dof_armature)


def _summed_down(model: mjx.Model, per_dof: jax.Array) -> jax.Array:
    """Per body, ``per_dof`` (nv, ...) summed over the dofs that move it (the dofs above it)."""
    return times(dof_subtrees(structure(model)).T, per_dof)


def dof_forces(model: mjx.Model, data: mjx.Data, wrenches: jax.Array) -> jax.Array:
    """The generalised force of one wrench per body (nbody, 6; ``cdof``'s order, angular then linear):
    each dof's motion axis against the wrenches of the bodies it moves, summed as a constant product."""
    return jnp.sum(data.cdof * times(dof_subtrees(structure(model)), wrenches), axis=-1)


def _com_vel_as_products(model: mjx.Model, data: mjx.Data) -> tuple:
    """``smooth.com_vel``'s body velocities and motion axes' rates: sums of the dofs' motions above."""
    rows = _rows_of(model)
    motions = data.cdof * data.qvel[:, None]
    frame_velocity = times(rows.moved_before.T, motions)  # each dof's frame's, before the dof moves it
    return _summed_down(model, motions), jax.vmap(mjx_math.motion_cross)(frame_velocity, data.cdof)


def _rne_as_products(model: mjx.Model, data: mjx.Data, with_acceleration: bool) -> jax.Array:
    """``smooth.rne``'s bias forces: the bodies' accelerations summed down the tree, their forces up it."""
    gravity = jnp.zeros(3) if model.opt.disableflags & types.DisableBit.GRAVITY else -model.opt.gravity
    accelerations = data.cdof_dot * data.qvel[:, None]
    if with_acceleration:
        accelerations = accelerations + data.cdof * data.qacc[:, None]
    acceleration = (jnp.concatenate([jnp.zeros(3), gravity]).astype(accelerations.dtype)
                    + _summed_down(model, accelerations))

    def force(cinert, acceleration, velocity):
        return mjx_math.inert_mul(cinert, acceleration) + mjx_math.motion_cross_force(
            velocity, mjx_math.inert_mul(cinert, velocity))

    return dof_forces(model, data, jax.vmap(force)(data._impl.cinert, acceleration, data.cvel))


def _subtree_vel_as_products(model: mjx.Model, data: mjx.Data) -> tuple:
    """``smooth.subtree_vel``'s subtree linear velocities and angular momenta, its two scans over the tree as
    products: the momenta are each body's own (its spin, and its motion about its subtree's centre) summed
    over the subtree, and each edge's (a child subtree's motion about its parent's) over the subtree below."""
    rows = _rows_of(model)
    angular, linear = data.cvel[:, :3], data.cvel[:, 3:]
    linear = linear - jnp.cross(data.xipos - times(rows.root, data.subtree_com), angular)
    mass, subtree_mass = model.body_mass[:, None], model.body_subtreemass[:, None]
    linvel = times(rows.subtree, mass * linear) / jnp.maximum(mujoco.mjMINVAL, subtree_mass)
    # The world body has neither a motion about its subtree nor a parent: off_world.
    own = jnp.einsum("bij,bj,bkj,bk->bi", data.ximat, model.body_inertia, data.ximat, angular) + rows.off_world * (
        jnp.cross(data.xipos - data.subtree_com, mass * (linear - linvel)))
    edge = rows.off_world * jnp.cross(data.subtree_com - times(rows.parent, data.subtree_com),
                                      subtree_mass * (linvel - times(rows.parent, linvel)))
    return linvel, times(rows.subtree, own) + times(rows.below, edge)


def _subtree_vel_fields(model: mjx.Model, data: mjx.Data) -> tuple:
    moved = _subtree_vel(model, data)
    return moved._impl.subtree_linvel, moved._impl.subtree_angmom


def _com_pos_fields(model: mjx.Model, data: mjx.Data) -> tuple:
    placed = _com_pos(model, data)
    return placed.subtree_com, placed._impl.cinert, placed.cdof


def _crb_fields(model: mjx.Model, data: mjx.Data) -> tuple:
    summed = _crb(model, data)
    return summed._impl.crb, summed._impl.M


def _com_vel_fields(model: mjx.Model, data: mjx.Data) -> tuple:
    moved = _com_vel(model, data)
    return moved.cvel, moved.cdof_dot


def _rne_field(model: mjx.Model, data: mjx.Data, with_acceleration: bool) -> jax.Array:
    return _rne(model, data, with_acceleration).qfrc_bias


def _kept(fields, as_products):
    return values_kept(fields, lambda model, data, value, moving, vary: vary(as_products), reads=as_products)


_com_pos, _crb = smooth.com_pos, smooth.crb
_com_pos_kept, _crb_kept = _kept(_com_pos_fields, _com_pos_as_products), _kept(_crb_fields, _crb_as_products)
_com_vel, _rne = smooth.com_vel, smooth.rne
_com_vel_kept = _kept(_com_vel_fields, _com_vel_as_products)
_subtree_vel = smooth.subtree_vel
_subtree_vel_kept = _kept(_subtree_vel_fields, _subtree_vel_as_products)
_rne_kept = {flag: _kept(functools.partial(_rne_field, with_acceleration=flag),
                         functools.partial(_rne_as_products, with_acceleration=flag)) for flag in (False, True)}


def com_pos(model: mjx.Model, data: mjx.Data) -> mjx.Data:
    """MJX's ``smooth.com_pos``, differentiated through constant products."""
    if model.impl != types.Impl.JAX:
        return _com_pos(model, data)
    subtree_com, cinert, cdof = _com_pos_kept(model, data)
    return data.replace(subtree_com=subtree_com, cdof=cdof).tree_replace({"_impl.cinert": cinert})


def crb(model: mjx.Model, data: mjx.Data) -> mjx.Data:
    """MJX's ``smooth.crb``, differentiated through constant products."""
    if model.impl != types.Impl.JAX:
        return _crb(model, data)
    composite, mass_matrix = _crb_kept(model, data)
    return data.tree_replace({"_impl.crb": composite, "_impl.M": mass_matrix})


def com_vel(model: mjx.Model, data: mjx.Data) -> mjx.Data:
    """MJX's ``smooth.com_vel``, differentiated through constant products."""
    if model.impl != types.Impl.JAX:
        return _com_vel(model, data)
    cvel, cdof_dot = _com_vel_kept(model, data)
    return data.replace(cvel=cvel, cdof_dot=cdof_dot)


def rne(model: mjx.Model, data: mjx.Data, flg_acc: bool = False) -> mjx.Data:
    """MJX's ``smooth.rne``, differentiated through constant products."""
    if model.impl != types.Impl.JAX:
        return _rne(model, data, flg_acc)
    return data.replace(qfrc_bias=_rne_kept[bool(flg_acc)](model, data))


def subtree_vel(model: mjx.Model, data: mjx.Data) -> mjx.Data:
    """MJX's ``smooth.subtree_vel`` (the subtree sensors' velocities and momenta), differentiated through
    constant products."""
    if model.impl != types.Impl.JAX:
        return _subtree_vel(model, data)
    linvel, angmom = _subtree_vel_kept(model, data)
    return data.tree_replace({"_impl.subtree_linvel": linvel, "_impl.subtree_angmom": angmom})


# (owner, attribute, replacement) for constraint_derivatives' remedies.
REMEDIES = ((smooth, "com_pos", com_pos), (smooth, "crb", crb), (smooth, "com_vel", com_vel), (smooth, "rne", rne),
            (smooth, "subtree_vel", subtree_vel))
