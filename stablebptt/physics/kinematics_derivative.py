"""Body frames differentiated as the joints' twists summed down the tree.

MJX's ``smooth.kinematics`` places the bodies by scanning the tree level by level, gathering each
level's parents and scattering its results. Reverse mode runs that scan backwards with the
transposes of every gather and scatter, in every physics step (what it costs: docs/performance.md,
"The position stage differentiated without the tree's scans").

The derivative has a closed form. A change of joint j's coordinates turns everything below j as a
rigid motion, a twist (w, v) about the world's origin (a point x moves by v + w x x): a hinge turns
about its world axis through its anchor, a slide moves along its axis, a ball or a free joint turns
by the rotation of its quaternion's tangent. A body's frame moves by the sum of the twists of the
joints above it, a joint's frame by those of the joints before it - sums of a constant 0/1 matrix
times the joints' twists. MuJoCo's rules make this exact for every tree it compiles: a free
joint hangs from the world, and no rotation follows a ball joint on its body, so the body's frame is
the ball's. ``REMEDIES`` give MJX's function that derivative while its values stay MJX's own, bit for
bit; a derivative in the model's numbers stays MJX's own.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from stablebptt.physics.mjx_internals import mjx, smooth, types
from stablebptt.physics.scene_terms import BALL, FREE, HINGE, SLIDE
from stablebptt.physics.tree_maps import Structure, joints_moved, picks, structure, subtree
from stablebptt.physics.values_kept import times, values_kept

_MOVED_BY_TWISTS = frozenset({"[1].qpos", "[1].mocap_pos", "[1].mocap_quat"})


class _Tree(NamedTuple):
    """A tree's constant maps: what the twists of its joints move, and where its coordinates lie."""
    moves_body: np.ndarray  # (njnt, nbody): joint j moves body b
    moves_joint: np.ndarray  # (njnt, njnt): joint i moves joint j's anchor and axis
    scalar: np.ndarray      # (njnt, nq): the coordinate of each hinge and slide
    hinge: np.ndarray       # (njnt, 1) 0/1
    slide: np.ndarray       # (njnt, 1) 0/1
    turning: tuple          # (joint, qpos address, is free) of each ball and free joint
    turning_rows: np.ndarray  # (njnt, nturning): their rows
    free_rows: np.ndarray   # (njnt, nturning): the free joints' rows, whose anchors move with their translation
    mocap_rows: np.ndarray  # (nbody, nmocap)
    frame_rows: np.ndarray  # (2 nbody + ngeom + nsite, nbody): the body of each frame, as _frames orders them


@functools.lru_cache(maxsize=64)
def _tree(tree: Structure) -> _Tree:
    kinds, bodies, addresses = (np.asarray(tree.joint_types, int), np.asarray(tree.joint_bodies, int),
                                tree.joint_addresses)
    njnt, nbody = len(kinds), len(tree.parents)
    scalar = np.zeros((njnt, tree.nq), np.float32)
    for joint in np.nonzero(np.isin(kinds, (HINGE, SLIDE)))[0]:
        scalar[joint, addresses[joint]] = 1.0
    turning = tuple((int(joint), int(addresses[joint]), bool(kinds[joint] == FREE))
                    for joint in np.nonzero(np.isin(kinds, (FREE, BALL)))[0])
    turning_rows = picks([joint for joint, _, _ in turning], njnt).T
    nmocap = sum(mocap_id >= 0 for mocap_id in tree.mocap_ids)
    mocap_rows = picks([tree.mocap_ids.index(mocap_id) for mocap_id in range(nmocap)], nbody).T
    frame_rows = picks([*range(nbody), *range(nbody), *tree.geom_bodies, *tree.site_bodies], nbody)
    return _Tree(subtree(tree)[bodies].astype(np.float32), joints_moved(tree).astype(np.float32), scalar,
                 (kinds == HINGE).astype(np.float32)[:, None], (kinds == SLIDE).astype(np.float32)[:, None],
                 turning, turning_rows, turning_rows * np.asarray([free for _, _, free in turning], np.float32),
                 mocap_rows, frame_rows)


def _tree_of(model: mjx.Model) -> _Tree:
    return _tree(structure(model))


def _frames(model: mjx.Model) -> tuple[tuple[str, str], ...]:
    """The (position, rotation) fields of the frames a body carries: its own, its inertia's, its geoms', its sites'."""
    return ((("xpos", "xmat"), ("xipos", "ximat")) + ((("geom_xpos", "geom_xmat"),) if model.ngeom else ())
            + ((("site_xpos", "site_xmat"),) if model.nsite else ()))


def _written(model: mjx.Model) -> tuple[str, ...]:
    """The data's fields ``smooth.kinematics`` writes."""
    return (("qpos", "xanchor", "xaxis", "xpos", "xquat", "xmat", "xipos", "ximat")
            + tuple(field for frame in _frames(model)[2:] for field in frame))  # the geoms' and sites' frames


def _quat_mul(u: jax.Array, v: jax.Array) -> jax.Array:
    (a, x), (b, y) = (u[..., :1], u[..., 1:]), (v[..., :1], v[..., 1:])
    return jnp.concatenate([a * b - jnp.sum(x * y, -1, keepdims=True), a * y + b * x + jnp.cross(x, y)], -1)


def _conjugate(q: jax.Array) -> jax.Array:
    return q * jnp.array([1.0, -1.0, -1.0, -1.0], q.dtype)


def _unit_tangent(quaternion: jax.Array, tangent: jax.Array) -> jax.Array:
    """The tangent of ``quaternion / |quaternion|`` (MJX normalises free and ball joints' quaternions)."""
    norm = jnp.linalg.norm(quaternion)
    unit = quaternion / norm
    return (tangent - unit * jnp.dot(unit, tangent)) / norm


def _turned(twist: jax.Array, points: jax.Array, frames: jax.Array):
    """What twists (n, 6) do to points (n, 3) and to the columns of rotation matrices (n, 3, 3)."""
    w, v = twist[:, :3], twist[:, 3:]
    return v + jnp.cross(w, points), jnp.cross(w[:, :, None], frames, axis=1)


def _frames_tangent(model: mjx.Model, data: mjx.Data, value: tuple, moving: frozenset, vary) -> tuple:
    """The tangent of ``smooth.kinematics``'s written fields (``value``, MJX's) by the joints' twists."""
    if not moving <= _MOVED_BY_TWISTS:
        return vary(_kinematics)
    tree = _tree_of(model)
    fields = dict(zip(_written(model), value))
    dq = vary(lambda model, data: data.qpos) if "[1].qpos" in moving else jnp.zeros_like(data.qpos)
    along = times(tree.scalar, dq)[:, None]  # each hinge's and slide's coordinate
    w = fields["xaxis"] * (tree.hinge * along)
    twists = jnp.concatenate([w, jnp.cross(fields["xanchor"], w) + fields["xaxis"] * (tree.slide * along)], -1)
    qpos_tangent = dq
    if tree.turning:
        turned, translations = [], []
        for joint, address, free in tree.turning:
            start = address + 3 if free else address
            unit = fields["qpos"][start:start + 4]
            unit_dot = _unit_tangent(data.qpos[start:start + 4], dq[start:start + 4])
            qpos_tangent = qpos_tangent.at[start:start + 4].set(unit_dot)
            if free:  # about the body's origin, which its translation carries
                w = 2.0 * _quat_mul(unit_dot, _conjugate(unit))[1:]
                translation = dq[address:address + 3]
                v = translation + jnp.cross(fields["xanchor"][joint], w)
            else:  # the quaternion turns the body's frame (no rotation follows it), about the joint's anchor
                w = fields["xmat"][model.jnt_bodyid[joint]] @ (2.0 * _quat_mul(_conjugate(unit), unit_dot)[1:])
                translation, v = jnp.zeros(3, dq.dtype), jnp.cross(fields["xanchor"][joint], w)
            turned.append(jnp.concatenate([w, v]))
            translations.append(translation)
        twists = twists + times(tree.turning_rows, jnp.stack(turned))
    bodies = times(tree.moves_body.T, twists)
    if model.nmocap and moving & {"[1].mocap_pos", "[1].mocap_quat"}:
        position_dot, quaternion_dot = vary(lambda model, data: (data.mocap_pos, data.mocap_quat))
        unit = jax.vmap(lambda q: q / jnp.linalg.norm(q))(data.mocap_quat)
        w = 2.0 * _quat_mul(jax.vmap(_unit_tangent)(data.mocap_quat, quaternion_dot), _conjugate(unit))[:, 1:]
        bodies = bodies + times(tree.mocap_rows, jnp.concatenate([w, position_dot + jnp.cross(data.mocap_pos, w)], -1))
    joints = times(tree.moves_joint.T, twists)
    anchor_dot = joints[:, 3:] + jnp.cross(joints[:, :3], fields["xanchor"])
    if tree.turning:
        anchor_dot = anchor_dot + times(tree.free_rows, jnp.stack(translations))
    tangents = {"qpos": qpos_tangent, "xanchor": anchor_dot, "xaxis": jnp.cross(joints[:, :3], fields["xaxis"])}
    tangents["xquat"] = 0.5 * _quat_mul(jnp.concatenate([jnp.zeros_like(bodies[:, :1]), bodies[:, :3]], -1),
                                        fields["xquat"])
    # Every frame a body carries turned at once, one product and one pair of cross products: in reverse mode
    # one transpose each rather than a sum of the cotangents of several.
    frames = _frames(model)
    points, rotations = _turned(times(tree.frame_rows, bodies), jnp.concatenate([fields[p] for p, _ in frames]),
                                jnp.concatenate([fields[r] for _, r in frames]))
    ends = np.cumsum([len(fields[p]) for p, _ in frames])[:-1]
    for (position, rotation), moved, turned in zip(frames, jnp.split(points, ends), jnp.split(rotations, ends)):
        tangents[position], tangents[rotation] = moved, turned
    return tuple(tangents[name] for name in _written(model))


_original = smooth.kinematics


def _kinematics(model: mjx.Model, data: mjx.Data) -> tuple:
    placed = _original(model, data)
    return tuple(getattr(placed, name) for name in _written(model))


_kept = values_kept(_kinematics, _frames_tangent, reads=lambda model, data: ())


def kinematics(model: mjx.Model, data: mjx.Data) -> mjx.Data:
    """MJX's ``smooth.kinematics``, its derivative the joints' twists summed down the tree."""
    if model.impl != types.Impl.JAX:
        return _original(model, data)
    return data.replace(**dict(zip(_written(model), _kept(model, data))))


# (owner, attribute, replacement) for constraint_derivatives' remedies.
REMEDIES = ((smooth, "kinematics", kinematics),)
