"""MJX's solves with the mass matrix differentiated as linear solves, not through the matrix's factor.

MJX factors a dense mass matrix M (``smooth.factor_m``: a Cholesky factor) and solves with the factor
(``smooth.solve_m``), for the smooth acceleration and again in the Euler integrator's damping. As
written, the derivative runs through the factorisation: the tangent of a Cholesky factor takes
triangular solves with the whole matrix on both sides, and reverse mode transposes them. The solution
x = M^-1 b has the tangent M^-1 (db - dM x): one more solve with the factor at hand, on a vector.
``REMEDIES`` give MJX's two functions that derivative; their values stay MJX's own, bit for bit. The
factor itself (``qLD``) then carries no derivative: code that differentiates it rather than a solve with
it gets zero. A sparse mass matrix (MJX's choice from 60 dofs) keeps MJX's own.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.ad_checkpoint import checkpoint_name

from stablebptt.physics.mjx_internals import mjx, smooth, support, types
from stablebptt.physics.values_kept import KEPT_VALUES

_factor_m, _solve_m = smooth.factor_m, smooth.solve_m


@jax.custom_jvp
def _solved(mass: jax.Array, factor: jax.Array, rhs: jax.Array) -> jax.Array:
    """M^-1 rhs from M's Cholesky factor, as MJX solves it."""
    return jax.scipy.linalg.cho_solve((factor, False), rhs)


@_solved.defjvp
def _solved_tangent(primals, tangents):
    mass, factor, rhs = primals
    mass_dot, _, rhs_dot = tangents  # the factor's tangent is M's, already in mass_dot
    solution = checkpoint_name(_solved(mass, factor, rhs), KEPT_VALUES)
    # HIGHEST: on a GPU a float32 matmul may round to TF32; this one is a matrix times a vector.
    moved = jnp.matmul(mass_dot, solution, precision=jax.lax.Precision.HIGHEST)
    # The solve itself again, not a bare cho_solve: the factor carries no derivative, so a second derivative
    # takes M's through this rule.
    return solution, _solved(mass, factor, rhs_dot - moved)


def _dense(model: mjx.Model) -> bool:
    return model.impl == types.Impl.JAX and not support.is_sparse(model)


def factor_m(model: mjx.Model, data: mjx.Data) -> mjx.Data:
    """MJX's ``smooth.factor_m``, its factor without a derivative where M is dense (``solve_m`` has M's)."""
    if not _dense(model):
        return _factor_m(model, data)
    mass = data._impl.M
    held = _factor_m(model, data.tree_replace({"_impl.M": jax.lax.stop_gradient(mass)}))
    # Named: the solves' tangents read the factor, which a recomputed step then keeps rather than factoring again.
    return held.tree_replace({"_impl.M": mass, "_impl.qLD": checkpoint_name(held._impl.qLD, KEPT_VALUES)})


def solve_m(model: mjx.Model, data: mjx.Data, x: jax.Array) -> jax.Array:
    """MJX's ``smooth.solve_m``, differentiated as M^-1 x where M is dense."""
    if not _dense(model):
        return _solve_m(model, data, x)
    return _solved(data._impl.M, data._impl.qLD, x)


# (owner, attribute, replacement) for constraint_derivatives' remedies.
REMEDIES = ((smooth, "factor_m", factor_m), (smooth, "solve_m", solve_m))
