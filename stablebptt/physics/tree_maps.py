"""A tree's constant maps, built once per model structure and shared by the derivatives that sum over it.

``structure(model)`` reads the model's index arrays into a hashable ``Structure``, the key under which
each derivative caches what it builds from them; ``subtree``, ``root``, ``dof_subtrees`` and
``joints_moved`` are the maps they share, ``picks`` the one-hot matrices that select rows by index.
"""
from __future__ import annotations

import functools
from typing import NamedTuple, Sequence

import numpy as np

from stablebptt.physics.mjx_internals import mjx
from stablebptt.physics.scene_terms import subtree_mask


class Structure(NamedTuple):
    """A model's tree as index tuples: what its constant maps depend on, and nothing else."""
    parents: tuple         # body_parentid
    roots: tuple           # body_rootid
    dof_bodies: tuple      # dof_bodyid
    dof_joints: tuple      # dof_jntid
    joint_types: tuple     # jnt_type
    joint_bodies: tuple    # jnt_bodyid
    joint_addresses: tuple  # jnt_qposadr
    nq: int
    mocap_ids: tuple       # body_mocapid
    geom_bodies: tuple     # geom_bodyid
    site_bodies: tuple     # site_bodyid


def structure(model: mjx.Model) -> Structure:
    def indices(array) -> tuple:
        return tuple(int(i) for i in np.asarray(array))
    return Structure(indices(model.body_parentid), indices(model.body_rootid), indices(model.dof_bodyid),
                     indices(model.dof_jntid), indices(model.jnt_type), indices(model.jnt_bodyid),
                     indices(model.jnt_qposadr), int(model.nq), indices(model.body_mocapid),
                     indices(model.geom_bodyid), indices(model.site_bodyid))


def picks(indices: Sequence[int], size: int) -> np.ndarray:
    """``rows[i, indices[i]] = 1``: times an array of ``size`` rows, the rows ``indices`` names."""
    return np.eye(size, dtype=np.float32)[list(indices)]


@functools.lru_cache(maxsize=64)
def subtree(tree: Structure) -> np.ndarray:
    """(nbody, nbody) bool: body c hangs from body b or is b."""
    return subtree_mask(np.asarray(tree.parents))


@functools.lru_cache(maxsize=64)
def root(tree: Structure) -> np.ndarray:
    """(nbody, nbody) 0/1: each body's tree's root."""
    return picks(tree.roots, len(tree.parents))


@functools.lru_cache(maxsize=64)
def dof_subtrees(tree: Structure) -> np.ndarray:
    """(nv, nbody) 0/1: body b lies in the subtree of dof j's body (j moves b)."""
    return subtree(tree)[list(tree.dof_bodies)].astype(np.float32)


@functools.lru_cache(maxsize=64)
def joints_moved(tree: Structure) -> np.ndarray:
    """(njnt, njnt) bool: joint i moves joint j's frame (i's body is above j's, or i comes first on their body)."""
    bodies = np.asarray(tree.joint_bodies, int)
    earlier = np.arange(len(bodies))[:, None] < np.arange(len(bodies))[None, :]
    return subtree(tree)[bodies][:, bodies] & ((bodies[:, None] != bodies[None, :]) | earlier)
