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
from mujoco.mjx._src import collision_driver, constraint, passive, smooth, solver  # noqa: E402
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

__all__ = ["mjx", "collision_driver", "constraint", "passive", "smooth", "solver", "forward", "types"]
