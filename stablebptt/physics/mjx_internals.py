"""The private parts of MJX this project relies on, in one place.

``scene`` runs MJX's pipeline stage by stage (only the stages a scene needs)
and asks MJX's collision table and enum types what it can simulate;
``constraint_derivatives`` differentiates its solver implicitly and remedies
derivative traps in its solver and collision modules. Those live in
``mujoco.mjx._src``, which has no stability promise: they were written against
``WRITTEN_FOR``, and ``check_version`` names a different installed MJX on stderr
once. Importing this module changes nothing in MJX.
"""
from __future__ import annotations

import contextlib
import functools
import io
import sys
from importlib.metadata import PackageNotFoundError, version

WRITTEN_FOR = "3.17.0"  # mujoco-mjx

# MJX prints "Failed to import warp" on stdout when the (gradient-free) Warp
# backend is absent: keep that out of users' output.
with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx  # noqa: F401
from mujoco.mjx._src import (  # noqa: E402
    collision_convex,
    collision_driver,
    constraint,
    forward,  # noqa: E402
    passive,
    sensor,
    smooth,
    solver,
    support,
    types,  # noqa: E402
)
from mujoco.mjx._src import math as mjx_math  # noqa: E402


def installed_version() -> str:
    try:
        return version("mujoco-mjx")
    except PackageNotFoundError:
        return "unknown"


@functools.cache
def check_version() -> bool:
    """Whether the installed MJX is the one these internals were written for; says so on stderr once if not."""
    if installed_version() == WRITTEN_FOR:
        return True
    print(f"warning: stablebptt uses MJX internals written for mujoco-mjx {WRITTEN_FOR}; installed is "
          f"{installed_version()} (constraints.txt lists the tested set)", file=sys.stderr)
    return False


__all__ = ["mjx", "collision_convex", "collision_driver", "constraint", "passive", "sensor", "smooth", "solver",
           "support", "forward", "types", "mjx_math", "check_version"]
