"""The private parts of MJX this project relies on, in one place.

``scene.make_step`` runs MJX's pipeline stage by stage (only the stages a scene
needs) and ``scene.check_supported`` asks MJX's collision table and enum types
what it can simulate. Those live in ``mujoco.mjx._src``, which has no stability
promise: they were written against ``WRITTEN_FOR`` and a different MJX is
named on stderr once, when this module is first imported.
"""
from __future__ import annotations

import contextlib
import io
import sys
from importlib.metadata import PackageNotFoundError, version

import jax
import jax.numpy as jnp

WRITTEN_FOR = "3.17.0"  # mujoco-mjx

# MJX prints "Failed to import warp" on stdout when the (gradient-free) Warp
# backend is absent, which it always is here: keep that out of users' output.
with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx  # noqa: F401
from mujoco.mjx._src import collision_convex, collision_driver, constraint, passive, smooth, solver, support  # noqa: E402
from mujoco.mjx._src import forward  # noqa: E402
from mujoco.mjx._src import types  # noqa: E402


def installed_version() -> str:
    try:
        return version("mujoco-mjx")
    except PackageNotFoundError:
        return "unknown"


if installed_version() != WRITTEN_FOR:
    print(f"warning: stablebptt uses MJX internals written for mujoco-mjx {WRITTEN_FOR}; installed is "
          f"{installed_version()} (constraints.txt lists the tested set)", file=sys.stderr)


@jax.custom_jvp
def _sqrt_flat_at_zero(x):
    return jnp.sqrt(x)


@_sqrt_flat_at_zero.defjvp
def _sqrt_flat_at_zero_jvp(primals, tangents):
    (x,), (x_dot,) = primals, tangents
    root = jnp.sqrt(x)
    return root, jnp.where(x > 0, x_dot / (2 * jnp.where(x > 0, root, 1.0)), 0.0)


# MJX's elliptic-cone line search takes the square root of a contact's squared
# tangential force, exactly 0 for a contact that does not slide: its slope there
# is 0 / 0 and turns every forward-mode step Jacobian into NaN, although the
# terms it feeds are masked out at 0. MJX's solver module alone gets a square
# root whose slope at 0 is 0; values are unchanged.
solver.jp = type(jnp)("jax.numpy, square root flat at zero")
solver.jp.__dict__.update({**vars(jnp), "sqrt": _sqrt_flat_at_zero})

@jax.custom_jvp
def _quotient_carrier(deriv_0, deriv_1):
    return deriv_0


@_quotient_carrier.defjvp
def _quotient_carrier_jvp(primals, tangents):
    (deriv_0, deriv_1), (deriv_0_dot, deriv_1_dot) = primals, tangents
    return deriv_0, deriv_0_dot - (deriv_0 / deriv_1) * deriv_1_dot


_ls_point_create = solver._LSPoint.create.__func__


def _ls_point_create_stable(cls, *args, **kwargs):
    point = _ls_point_create(cls, *args, **kwargs)
    return point.replace(deriv_0=_quotient_carrier(point.deriv_0, point.deriv_1),
                         deriv_1=jax.lax.stop_gradient(point.deriv_1))


# MJX's line search steps to alpha - deriv_0 / deriv_1, and those are the only
# differentiable use of a point's two derivatives (everywhere else they are
# compared). The slope of a quotient in deriv_1 is -deriv_0 / deriv_1**2, which
# XLA evaluates as deriv_0 / (deriv_1 * deriv_1): where the search direction is
# rounding noise (no constraint active, the unconstrained acceleration already
# optimal), deriv_1 is ~1e-20 and its square underflows float32 to 0, giving
# inf, and NaN against the zero cotangent such a step gets. Points carry the
# same values, but deriv_1's tangent moves into deriv_0's as
# d deriv_0 - (deriv_0 / deriv_1) d deriv_1 (deriv_1 itself gets none), so the
# quotient's derivative, (d deriv_0 - ratio d deriv_1) / deriv_1, is unchanged
# and has no square, in forward and reverse mode alike.
solver._LSPoint.create = classmethod(_ls_point_create_stable)


def _closest_segment_point_plane_stable(a, b, p0, plane_normal):
    n = plane_normal
    along = jnp.sum(n * (b - a))
    denominator = along + 1e-6 * (along == 0.0)
    numerator = jnp.sum(p0 * n) - jnp.sum(n * a)
    raw = jax.lax.stop_gradient(numerator / denominator)
    on_segment = (raw >= 0) & (raw <= 1)
    t = jnp.where(on_segment, numerator / jnp.where(on_segment, denominator, 1.0), jnp.clip(raw, 0, 1))
    return a + t * (b - a)


# MJX clips a capsule's or box's edge against a convex body's side planes at
# t = distance / (normal . edge), clipped to [0, 1]. For a plane nearly
# parallel to the edge the quotient is huge and clipped away, so its cotangent
# is 0, but the quotient's slope in the denominator, -t / denominator, is inf in
# float32: 0 x inf gives NaN in reverse mode (manipulator, stacker). Here a
# clipped t is a constant, as its derivative already says, and the quotient is
# only formed where it lands on the segment; values are unchanged.
collision_convex._closest_segment_point_plane = _closest_segment_point_plane_stable

__all__ = ["mjx", "collision_convex", "collision_driver", "constraint", "passive", "smooth", "solver", "support", "forward", "types"]
