"""Contacts smoothed in the derivative alone: the step simulates the model as the file says, and its
derivative is that of the same step through a model whose contacts act from a distance and are
softer (``ContactSmoothing``).

The exact derivative of a contact step says nothing about a contact that has not yet been made (a
foot above the ground has no constraint row) and is as stiff as the contact itself where it is made.
The smoothed model gives each contact a margin (it pushes from ``margin`` metres away, as MuJoCo's
geom margin does) and a longer time constant (``softness`` times the file's): its derivative sees
contacts about to be made, at a lower stiffness. Values are the exact step's, bit for bit; only
tangents and cotangents come from the smoothed model, taken at the true state (the straight-through
estimator of backward-only smoothing).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable

import jax
import mujoco
import numpy as np

from stablebptt.errors import InputError, keywords_named
from stablebptt.physics.mjx_internals import mjx
from stablebptt.physics.mjx_internals import types as mjx_types


@keywords_named
@dataclasses.dataclass(frozen=True)
class ContactSmoothing:
    """How the derivative's model softens contacts: ``margin`` metres added to every contact's
    margin, its time constant times ``softness``. ``margin=0, softness=1`` is the file's model."""

    margin: float = 0.0
    softness: float = 1.0

    def __post_init__(self):
        check_smoothing(self.margin, self.softness, "ContactSmoothing.margin", "ContactSmoothing.softness")

    @property
    def exact(self) -> bool:
        return self.margin == 0 and self.softness == 1


def check_smoothing(margin, softness, margin_name: str, softness_name: str) -> None:
    """``InputError`` naming the option (``margin_name``, ``softness_name``) where a smoothing is none."""
    number = lambda value: isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)  # noqa: E731
    if not (number(margin) and margin >= 0):
        raise InputError(f"{margin_name} must be a number of metres >= 0 (0: contacts act as the file says), "
                         f"got {margin!r}")
    if not (number(softness) and softness >= 1):
        raise InputError(f"{softness_name} must be a number >= 1 (1: the file's time constants), got {softness!r}")


def _like(field, values):
    """``values`` as the kind of array ``field`` is (MJX keeps some model fields in NumPy)."""
    return np.asarray(values, dtype=np.asarray(field).dtype) if isinstance(field, np.ndarray) else \
        jax.numpy.asarray(values, dtype=field.dtype)


def softer(solref, softness: float, shortest: float = 0.0) -> np.ndarray:
    """Solrefs ``[..., 2]`` with time constants ``softness`` times longer: in MuJoCo's standard form
    (time constant, damping ratio) the time constant MuJoCo simulates, at least ``shortest`` (twice the
    time step where its refsafe flag is on), times ``softness``; in its direct form (negated stiffness
    and damping) the stiffness over ``softness`` squared and the damping over ``softness``, as a time
    constant that much longer would make them."""
    solref = np.array(solref, dtype=np.float64)
    direct = solref[..., 0] < 0
    solref[..., 0] = np.where(direct, solref[..., 0] / softness ** 2, np.maximum(solref[..., 0], shortest) * softness)
    solref[..., 1] = np.where(direct, solref[..., 1] / softness, solref[..., 1])
    return solref


def smoothed_model(model: mjx.Model, smoothing: ContactSmoothing) -> mjx.Model:
    """``model`` with its contacts as the derivative sees them: every contact's margin widened by
    ``smoothing.margin`` (a geom pair's margin is the sum of its geoms': half to each geom, all to an
    explicit pair's) and time constants lengthened by ``smoothing.softness``."""
    refsafe = not int(model.opt.disableflags) & int(mujoco.mjtDisableBit.mjDSBL_REFSAFE)
    shortest = 2 * float(model.opt.timestep) if refsafe else 0.0
    return model.replace(
        geom_margin=_like(model.geom_margin, np.asarray(model.geom_margin) + smoothing.margin / 2),
        geom_solref=_like(model.geom_solref, softer(model.geom_solref, smoothing.softness, shortest)),
        pair_margin=_like(model.pair_margin, np.asarray(model.pair_margin) + smoothing.margin),
        pair_solref=_like(model.pair_solref, softer(model.pair_solref, smoothing.softness, shortest)))


def differentiated_through(exact: Callable, smoothed: Callable) -> Callable:
    """``exact``'s values with ``smoothed``'s derivative, both functions of the same arguments with
    outputs of the same structure. Reverse mode transposes the smoothed linearisation."""
    stepped = jax.custom_jvp(exact)

    def jvp(primals, tangents):
        _, tangents_out = jax.jvp(smoothed, primals, tangents)
        return exact(*primals), tangents_out

    stepped.defjvp(jvp)
    return stepped


# The geom pairs whose MJX collision measures each contact between closest points of smooth convex
# surfaces, or from a vertex fixed in its body to a plane: there the distance's closed form below is exact
# to first order. Pairs clipped face against face (box-box, meshes) are not: their points slide along edges.
_TYPE = mjx_types.GeomType
CLOSED_FORM_PAIRS = frozenset({(_TYPE.PLANE, _TYPE.SPHERE), (_TYPE.PLANE, _TYPE.CAPSULE), (_TYPE.PLANE, _TYPE.BOX),
                               (_TYPE.SPHERE, _TYPE.SPHERE), (_TYPE.SPHERE, _TYPE.CAPSULE),
                               (_TYPE.CAPSULE, _TYPE.CAPSULE)})


def distance_by_closed_form(data: mjx.Data, geoms: jax.Array, dist: jax.Array, pos: jax.Array,
                            frame: jax.Array) -> jax.Array:
    """``dist`` (contacts found from held data, one per row of ``geoms``, the pair's two geom ids) with the
    derivative d dist = n . (v2 - v1): the two geoms' bodies' velocities at the contact point ``pos``, along
    the normal ``frame[:, 0]`` (from geom 1 to geom 2), from ``data``'s geom poses.

    Exact to first order for ``CLOSED_FORM_PAIRS``: a witness point slides on its surface perpendicular
    to the normal, and the normal's own turn is perpendicular to the gap it measures, so neither moves
    the distance. Values are ``dist``'s, bit for bit: the form enters as ``x - stop_gradient(x)``."""
    normal, point = jax.lax.stop_gradient(frame[:, 0]), jax.lax.stop_gradient(pos)

    def moving_with(geom):  # the contact point fixed in the geom's frame: it moves as the body does
        position, rotation = data.geom_xpos[geom], data.geom_xmat[geom]
        in_geom = jax.numpy.einsum("cji,cj->ci", jax.lax.stop_gradient(rotation),
                                   point - jax.lax.stop_gradient(position))
        return position + jax.numpy.einsum("cij,cj->ci", rotation, in_geom)

    gap = jax.numpy.sum(normal * (moving_with(geoms[:, 1]) - moving_with(geoms[:, 0])), -1)
    return jax.lax.stop_gradient(dist) + (gap - jax.lax.stop_gradient(gap))


def geometry_held(collide: Callable) -> Callable:
    """``collide`` (an MJX collision function of one geom-type pair in ``CLOSED_FORM_PAIRS``: ``(model, data,
    key, geoms) -> (dist, pos, frame)``, ``ncon`` contacts a pair) run on held data, so that it has no
    derivative in the program: its points and frames held, its distances differentiated by
    ``distance_by_closed_form``."""
    def collide_held(model, data, key, geoms):
        dist, pos, frame = collide(model, jax.lax.stop_gradient(data), key, geoms)
        pairs = jax.numpy.repeat(jax.numpy.asarray(geoms), collide.ncon, axis=0)
        return distance_by_closed_form(data, pairs, dist, pos, frame), pos, frame
    collide_held.ncon = collide.ncon
    return collide_held
